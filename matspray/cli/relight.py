"""`matspray relight --run RUN --env NAME|PATH`: render the asset under a new light.

The run-folder glue lives here: which asset, which cameras, which files; `matspray.method.relight` only renders."""

from pathlib import Path

from matspray.cli.options import VARIANT_HELP, add_compute_arguments, given, hidden_alias, output_folder, refuse
from matspray.presets import light_names

ORBIT_FRAMES, ORBIT_FPS = 60, 24  # --views orbit: frames of the circle, and of the video per second


def add_relight_parser(parser) -> None:
    parser.add_argument(
        "--run",
        type=Path,
        required=True,
        help="run folder made by `matspray run`, or a .glb made by `matspray export --splats` (--views orbit)",
    )
    parser.add_argument(
        "--env",
        required=True,
        nargs="+",
        metavar="NAME|PATH",
        help=f"environment lights, each rendered in turn: a named light ({light_names()}) or a lat-long .exr/.hdr file",
    )
    parser.add_argument(
        "--views",
        choices=("test", "orbit"),
        default="test",
        help="test: the dataset's test cameras (default); orbit: a circle around the object, also as MP4",
    )
    parser.add_argument(
        "--out",
        type=output_folder,
        required=True,
        help="folder for the frames, VIEW_LIGHT.png (e.g. r_000_sunset.png, orbit_000_sunset.png), and with "
        "--views orbit a video per light, orbit_LIGHT.mp4",
    )
    parser.add_argument(
        "--resolution",
        type=int,
        metavar="PX",
        help="long side of the frames in pixels (default: the dataset's image size)",
    )
    hidden_alias(parser, "--size", "resolution", type=int)  # the name people try; image sizes are --resolution
    parser.add_argument(
        "--variant",
        help=VARIANT_HELP,
    )
    parser.add_argument("--frames", type=int, help=f"orbit: number of frames (default {ORBIT_FRAMES})")
    parser.add_argument("--fps", type=int, help=f"orbit: frames per second of the video (default {ORBIT_FPS})")
    parser.add_argument(
        "--background",
        choices=("transparent", "env"),
        default="transparent",
        help="transparent PNGs (default), or the environment itself behind the object",
    )
    parser.add_argument("--env-height", type=int, default=64, help="rows of the prefiltered light (default 64)")
    add_compute_arguments(parser)


def relight_run(
    run_dir,
    env,
    views: str,
    out_dir,
    variant: str | None = None,
    frames: int = ORBIT_FRAMES,
    fps: int = ORBIT_FPS,
    background: str = "transparent",
    env_height: int = 64,
    device="cpu",
    backend: str = "torch",
    resolution: int | None = None,
) -> list[Path]:
    """Render a run's asset under `env` (a light, or a list of them: names or files) for the dataset's test cameras
    or an orbit, `resolution` pixels on their long side (None: the dataset's size), on `device` with the rasterizer
    `backend` (both resolved); returns the files written: VIEW_LIGHT.png, and orbit_LIGHT.mp4 for an orbit."""
    from tqdm import tqdm

    from matspray.data import write_image
    from matspray.data.formats.video import write_video
    from matspray.data.images import linear_to_srgb
    from matspray.errors import ConfigError, optional_module
    from matspray.method.relight import background_radiance, render_relit
    from matspray.render.backend import rendering_with
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.render.shade.lights import load_envmap

    for flag, value, least in (("--frames", frames, 1), ("--fps", fps, 1), ("--env-height", env_height, 4)):
        if value < least:
            raise ConfigError(f"{flag} {value}: give {least} or more")
    if resolution is not None and not 8 <= resolution <= 8192:
        raise ConfigError(f"--resolution {resolution}: choose 8 to 8192 pixels")
    if views == "orbit":  # said before any frame is rendered, not after
        optional_module("imageio_ffmpeg", "video", "the orbit's video (relight --views orbit)")
    out_dir = Path(out_dir)
    lights = [load_envmap(spec) for spec in ([env] if isinstance(env, (str, Path)) else env)]  # all read first
    asset, cameras = relight_source(run_dir, views, variant, frames, device)
    if resolution is not None:
        cameras = [(name, c.scaled(resolution / max(c.width, c.height))) for name, c in cameras]
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, env_map in lights:
        light = EnvironmentMap.from_tensor(env_map.to(device), height=env_height, learnable=False)
        prefiltered = light.prefilter()
        video_frames = []
        for view_name, camera in tqdm(cameras, desc=f"relight [{name}]"):
            camera = camera.to(device)
            with rendering_with(backend):
                rgb, alpha = render_relit(asset, camera, prefiltered)
            if background == "env":
                rgb = rgb + background_radiance(light, camera) * (1 - alpha[..., None])
            rgb, alpha = rgb.cpu(), alpha.cpu()
            path = out_dir / f"{view_name}_{name}.png"
            if background == "env":
                write_image(path, rgb)
            else:
                write_image(path, rgb / alpha[..., None].clamp_min(1e-4), alpha)
            written.append(path)
            video_frames.append(linear_to_srgb(rgb))
        if views == "orbit":
            video = out_dir / f"orbit_{name}.mp4"
            write_video(video_frames, video, fps)
            written.append(video)
    return written


def relight_source(run_dir, views: str, variant: str | None, frames: int, device):
    """The asset to relight and its cameras [(name, Camera)]: of a run folder, or of a .glb that `matspray export
    --splats` wrote (its orbit only: it holds no dataset)."""
    from matspray.data import load_run_scene
    from matspray.errors import ConfigError, RunError, file_error
    from matspray.method.asset import read_asset
    from matspray.method.relight import orbit_cameras, spec_cameras
    from matspray.rundir import RunDir

    if Path(run_dir).suffix.lower() == ".glb":
        from matspray.export.splats import read_splats_asset

        if variant is not None:
            raise ConfigError("--variant is for run folders; a .glb holds one asset")
        splats = read_splats_asset(run_dir, device)
        if views == "test":
            raise file_error(Path(run_dir), "holds no test views", "use --views orbit")
        if not splats.view:
            raise file_error(Path(run_dir), "records no orbit", "export it again with `matspray export --splats`")
        return splats.asset, [(f"orbit_{i:03d}", c) for i, c in enumerate(spec_cameras(splats.view, frames))]
    run = RunDir(run_dir).require()
    asset = read_asset(run.asset_path(variant if variant is not None else run.default_variant()), device=device)
    scene = load_run_scene(run)
    if views == "test":
        if not scene.test:
            raise RunError(f"{run.dataset()['source']}: the dataset has no test views; use --views orbit")
        return asset, [(v.name, v.camera) for v in scene.test]
    reference, center, up = orbit_reference(run, scene)
    return asset, [(f"orbit_{i:03d}", c) for i, c in enumerate(orbit_cameras(reference, center, frames, up=up))]


def orbit_reference(run, scene):
    """What a run's orbit circles: its training cameras, the object's centre [3] and the cameras' up [3]."""
    import torch

    from matspray.method.masks import read_region
    from matspray.method.relight import cameras_up

    # a capture without masks: circle its object region, not the middle of everything the photos show
    region = read_region(run.path("masks"))
    center = torch.tensor(region.center) if region is not None else scene.bounds.mean(0)
    reference = [v.camera for v in scene.train]
    return reference, center, cameras_up(reference)


def relight_main(args) -> int:
    from matspray.device import out_of_memory_as_error
    from matspray.render.backend import compute_target

    if args.views != "orbit":
        refuse(given(args, ("--frames", "--fps")), "for --views orbit")
    device, backend = compute_target(args.device, args.backend)
    with out_of_memory_as_error("relight", device):
        written = relight_run(
            args.run,
            args.env,
            args.views,
            args.out,
            variant=args.variant,
            frames=ORBIT_FRAMES if args.frames is None else args.frames,
            fps=ORBIT_FPS if args.fps is None else args.fps,
            background=args.background,
            env_height=args.env_height,
            device=device,
            backend=backend,
            resolution=args.resolution,
        )
    print(f"wrote {len(written)} files to {args.out}")
    return 0
