"""`matspray geometry --data DATA --out RUN`: fit 3D Gaussians to the photos (RUN/geometry/)."""

from pathlib import Path

from matspray.cli.options import add_choice_argument, add_compute_arguments, add_setting_flags, output_folder
from matspray.cli.settings import add_set_argument
from matspray.presets import PRESETS, WORKING_SIZE


def add_geometry_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=output_folder, required=True, help="run folder; the stage writes RUN/geometry/")
    add_choice_argument(parser, "preset", PRESETS)
    add_setting_flags(parser, ["--downscale"])  # as `run` reads it
    add_set_argument(parser, "geometry.iterations=1000 seed=1")  # the geometry.* settings and the seed, as in `run`
    parser.add_argument(
        "--restart", action="store_true", help="discard an earlier checkpoint in RUN/geometry/ instead of resuming it"
    )
    parser.add_argument("--threads", type=int, default=0, help="CPU threads for torch (default: torch's choice)")
    add_compute_arguments(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def geometry_main(args) -> int:
    from matspray.cli.options import method_settings_from_args
    from matspray.cli.settings import settings_from_overrides
    from matspray.errors import ConfigError

    named = settings_from_overrides(
        args.overrides, args.preset, allowed=lambda k: k.startswith("geometry.") or k == "seed"
    )
    overrides = {key.split(".", 1)[-1]: value for key, value in named.items()}
    if args.threads < 0:
        raise ConfigError(f"--threads must be >= 0, got {args.threads}")

    import torch

    from matspray.data import load_scene
    from matspray.device import out_of_memory_as_error
    from matspray.errors import SettingError
    from matspray.geometry.config import preset
    from matspray.geometry.train import train_geometry
    from matspray.render.backend import compute_target, rendering_with
    from matspray.rundir import RunDir

    try:
        config = preset(args.preset, **overrides)
    except SettingError as exc:  # named as `run` names it, by the dotted setting `--set` takes
        raise SettingError(exc.setting if exc.setting == "seed" else f"geometry.{exc.setting}", exc.problem) from None
    device, backend = compute_target(args.device, args.backend)
    if args.threads:
        torch.set_num_threads(args.threads)
    # the photos `run` reads: larger ones brought to the preset's working size unless --downscale says otherwise
    downscale = method_settings_from_args(args).get("downscale")  # read as `run` reads it
    scene = load_scene(args.data, downscale=downscale, max_size=WORKING_SIZE[args.preset])
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
        ("psnr", "test PSNR (whole image)", "dB"),
        ("psnr_masked", "test PSNR (object)", "dB"),
        ("normal_error_deg", "normal error", "deg"),
    ):
        if metrics.get(key) is not None:
            print(f"{label}: {metrics[key]:.2f} {unit}")
    return 0
