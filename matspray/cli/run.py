"""`matspray run --data DATA --out RUN`: predict -> geometry -> lift -> refine, resuming finished stages."""

from pathlib import Path

from matspray.cli.options import VARIANT_CHOICES, add_method_arguments, build_config_from_args


def add_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=Path, required=True, help="run folder; finished stages in it are reused")
    parser.add_argument("--predictor", default="simulated", metavar="SPEC",
                        help="2D material maps: files:DIR, marigold, simulated[:paper|harsh|outliers] or ground-truth "
                        "(default: simulated, = simulated:paper, benchmarks only)")
    parser.add_argument("--variant", choices=VARIANT_CHOICES, nargs="+", default=["full"],
                        help="method variants to refine (the paper's ablations); default: full")
    parser.add_argument("--weights", help="marigold: pipeline folder")
    parser.add_argument("--severity", type=float, help="simulated: strength of the simulated failure modes (default 1)")
    parser.add_argument("--overwrite", action="store_true", help="reuse an --out folder made from another dataset")
    add_method_arguments(parser)


def run(args) -> int:
    from matspray.pipeline import Pipeline
    from matspray.variants import asset_stage

    options = {name: value for name, value in (("weights", args.weights), ("severity", args.severity)) if value is not None}
    config = build_config_from_args(args, predictor=args.predictor, predictor_options=options)
    pipeline = Pipeline(args.data, args.out, config, overwrite=args.overwrite)
    pipeline.run_all(args.variant)
    timings = pipeline.run.timings()
    print(f"method {config.method}; seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    for variant in args.variant:
        print(f"asset [{variant}]: {pipeline.run.path(asset_stage(variant), 'asset.ply')}")
    return 0
