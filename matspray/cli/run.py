"""`matspray run --data DATA --out RUN`: predict -> geometry -> lift -> refine, resuming finished stages."""

from pathlib import Path

VARIANT_CHOICES = ("full", "proj-average", "supervised", "no-softmax")


def add_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=Path, required=True, help="run folder; finished stages in it are reused")
    add_settings_arguments(parser)
    parser.add_argument("--overwrite", action="store_true", help="reuse an --out folder made from another dataset")


def add_settings_arguments(parser) -> None:
    """The run's settings (shared with `matspray batch`, which applies them to every object)."""
    parser.add_argument("--predictor", default="simulated", metavar="SPEC",
                        help="2D material maps: files:DIR, marigold, simulated or ground-truth (default: simulated, benchmarks only)")
    parser.add_argument("--preset", choices=("test", "demo", "paper"), default="demo",
                        help="test: tiny, for CI; demo: 2 CPU cores (default); paper: one GPU, the paper's settings")
    parser.add_argument("--variant", choices=VARIANT_CHOICES, nargs="+", default=["full"],
                        help="method variants to refine (the paper's ablations); default: full")
    parser.add_argument("--downscale", type=float, default=1.0, help="shrink images by this factor on load (default 1)")
    parser.add_argument("--geometry-iterations", type=int, help="override the preset's Gaussian Splatting iterations")
    parser.add_argument("--refine-iterations", type=int, help="override the preset's refinement iterations")
    parser.add_argument("--samples-per-side", type=int, help="override the preset's k (k x k lifting rays per pixel)")
    parser.add_argument("--min-support", type=float, metavar="SHARE",
                        help="a view counts for a Gaussian when it gets at least this share of the hits of its best view "
                             "(default 0.5; 0 counts every view with a hit)")
    parser.add_argument("--shadows", choices=("on", "off"), default="on",
                        help="on (default): bake each Gaussian's visibility and shadow the PBR shading with it; "
                             "off: the paper's unshadowed split-sum shading")
    parser.add_argument("--basecolor-loss", choices=("scale-invariant", "l1"), default="scale-invariant",
                        help="how refinement compares the rendered base color with the 2D maps: scale-invariant (default; "
                             "forgives each view's exposure error, the photometric loss sets the brightness) or plain l1")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda or cuda:N")
    parser.add_argument("--weights", help="marigold: pipeline folder")
    parser.add_argument("--severity", type=float, help="simulated: strength of the simulated failure modes (default 1)")


def config_from_args(args):
    from dataclasses import replace

    from matspray.errors import ConfigError
    from matspray.pipeline import preset_config

    config = preset_config(args.preset, downscale=args.downscale, seed=args.seed, device=args.device, predictor=args.predictor)
    options = {}
    if args.weights is not None:
        options["weights"] = args.weights
    if args.severity is not None:
        options["severity"] = args.severity
    config.predictor_options = options
    if args.shadows == "off":
        config.visibility = None
    if args.geometry_iterations is not None:
        from matspray.geometry.config import preset as geometry_preset

        if args.geometry_iterations < 1:
            raise ConfigError(f"--geometry-iterations must be >= 1, got {args.geometry_iterations}")
        config.geometry = geometry_preset(args.preset, seed=args.seed, iterations=args.geometry_iterations)
    if args.refine_iterations is not None:
        if args.refine_iterations < 0:
            raise ConfigError(f"--refine-iterations must be >= 0, got {args.refine_iterations}")
        config.refine = replace(config.refine, iterations=args.refine_iterations)
    config.refine = replace(config.refine, basecolor_loss=args.basecolor_loss)
    if args.samples_per_side is not None:
        if not 1 <= args.samples_per_side <= 32:
            raise ConfigError(f"--samples-per-side must be in 1..32, got {args.samples_per_side}")
        config.lift = replace(config.lift, samples_per_side=args.samples_per_side)
    if args.min_support is not None:
        if not 0.0 <= args.min_support <= 1.0:
            raise ConfigError(f"--min-support must be in [0, 1], got {args.min_support}")
        config.lift = replace(config.lift, min_support=args.min_support)
    return config


def run(args) -> int:
    from matspray.pipeline import Pipeline, asset_stage

    pipeline = Pipeline(args.data, args.out, config_from_args(args), overwrite=args.overwrite)
    pipeline.run_all(args.variant)
    timings = pipeline.run.timings()
    print("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    for variant in args.variant:
        print(f"asset [{variant}]: {pipeline.run.path(asset_stage(variant), 'asset.ply')}")
    return 0
