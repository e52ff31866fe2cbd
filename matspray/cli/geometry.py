"""`matspray geometry --data DATA --out RUN`: fit 3D Gaussians to the photos (RUN/geometry/)."""

from pathlib import Path

from matspray.cli.options import add_compute_arguments


def add_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=Path, required=True, help="run folder; the stage writes RUN/geometry/")
    parser.add_argument("--preset", default="demo", help="test | demo | paper (default: demo, 128 px on a CPU)")
    parser.add_argument(
        "--iterations", type=int, default=None, help="training steps (default: the preset's); the schedule follows"
    )
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: the preset's)")
    parser.add_argument(
        "--restart", action="store_true", help="discard an earlier checkpoint in RUN/geometry/ instead of resuming it"
    )
    parser.add_argument("--threads", type=int, default=0, help="CPU threads for torch (default: torch's choice)")
    add_compute_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from matspray.errors import ConfigError

    if args.iterations is not None and args.iterations < 1:
        raise ConfigError(f"--iterations must be >= 1, got {args.iterations}")
    if args.threads < 0:
        raise ConfigError(f"--threads must be >= 0, got {args.threads}")

    import torch

    from matspray.data import load_scene
    from matspray.device import compute_target, out_of_memory_as_error
    from matspray.geometry.config import preset
    from matspray.geometry.train import train_geometry
    from matspray.render.backend import rendering_with
    from matspray.rundir import RunDir

    overrides = {}
    if args.iterations is not None:
        overrides["iterations"] = args.iterations
    if args.seed is not None:
        overrides["seed"] = args.seed
    config = preset(args.preset, **overrides)
    device, backend = compute_target(args.device, args.backend)
    if args.threads:
        torch.set_num_threads(args.threads)
    scene = load_scene(args.data)
    out = args.out / "geometry"
    with (
        RunDir(args.out).hold(),
        rendering_with(backend),
        out_of_memory_as_error("geometry", device),
    ):  # held: refused while another process writes the run folder
        gaussians = train_geometry(scene, config, out, device=device, restart=args.restart, progress=not args.quiet)

    import json

    metrics = json.loads((out / "metrics.json").read_text())
    print(f"{len(gaussians)} Gaussians -> {out / 'gaussians.ply'} (on {device}, rasterizer {backend})")
    for key, label, unit in (
        ("psnr", "test PSNR (on white)", "dB"),
        ("psnr_masked", "test PSNR (object)", "dB"),
        ("normal_error_deg", "normal error", "deg"),
    ):
        if metrics.get(key) is not None:
            print(f"{label}: {metrics[key]:.2f} {unit}")
    return 0
