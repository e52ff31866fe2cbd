"""`matspray relight --run RUN --env NAME|PATH`: render the asset under a new light."""

from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--run", type=Path, required=True, help="run folder made by `matspray run`")
    parser.add_argument("--env", required=True, metavar="NAME|PATH",
                        help="environment light: a built-in name, a lat-long .exr/.hdr file, or a name in ../shared/data/hdri")
    parser.add_argument("--views", choices=("test", "orbit"), default="test",
                        help="test: the dataset's test cameras (default); orbit: a circle around the object, also as MP4")
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNG frames (and orbit.mp4)")
    parser.add_argument("--variant", default="full", help="which asset of the run (default: full)")
    parser.add_argument("--frames", type=int, default=60, help="orbit: number of frames (default 60)")
    parser.add_argument("--fps", type=int, default=24, help="orbit: frames per second of the video (default 24)")
    parser.add_argument("--background", choices=("transparent", "env"), default="transparent",
                        help="transparent PNGs (default), or the environment itself behind the object")
    parser.add_argument("--env-height", type=int, default=64, help="rows of the prefiltered light (default 64)")


def run(args) -> int:
    from matspray.device import configure_threads

    configure_threads()
    from matspray.relight import relight_run

    written = relight_run(args.run, args.env, args.views, args.out, variant=args.variant, frames=args.frames, fps=args.fps,
                          background=args.background, env_height=args.env_height)
    print(f"wrote {len(written)} files to {args.out}")
    return 0
