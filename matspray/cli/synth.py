"""`matspray synth --out DIR`: a synthetic benchmark object rendered by Mitsuba 3, with ground truth."""

from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output folder (Blender layout + ground truth)")
    parser.add_argument("--shape", default="random",
                        help="sphere, rounded-cube, torus, capsule, blob, composite, or random (picked from the seed; default)")
    parser.add_argument("--seed", type=int, default=0, help="seed of shape, materials, cameras and renders (default 0)")
    parser.add_argument("--res", type=int, default=128, help="image width and height in pixels (default 128)")
    parser.add_argument("--views", type=int, default=40, help="training views (default 40)")
    parser.add_argument("--test-views", type=int, default=10, help="test views, each also relit (default 10)")
    parser.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel (default 64)")
    parser.add_argument("--env", default="sky",
                        help="training light: built-in name, .exr/.hdr lat-long file, or shared HDRI name (default sky)")
    parser.add_argument("--relight-env", nargs="+", default=None, metavar="ENV",
                        help="lights of the relit test views (default: two built-ins other than --env)")
    parser.add_argument("--env-height", type=int, default=128, help="lights are rendered at H x 2H (default 128)")
    parser.add_argument("--overwrite", action="store_true", help="replace a different scene already in --out")


def run(args) -> int:
    from matspray.synth import SynthConfig, make_object

    config = SynthConfig(
        shape=args.shape, seed=args.seed, resolution=args.res, train_views=args.views, test_views=args.test_views,
        spp=args.spp, env=args.env, relight_envs=args.relight_env, env_height=args.env_height, overwrite=args.overwrite,
    )
    result = make_object(config, args.out)
    print(f"{result.out}: {result.shape} under {result.train_env}, relit under {', '.join(result.relight_envs) or 'nothing'} "
          f"({result.variant}, {result.seconds:.1f} s)")
    return 0
