"""`matspray run --data DATA --out RUN`: predict -> geometry -> lift -> refine, resuming finished stages."""

from pathlib import Path

from matspray.cli.options import (
    SETTING_FLAGS,
    add_method_arguments,
    add_run_arguments,
    build_config_from_args,
    output_folder,
    predictor_options_from_args,
)
from matspray.cli.settings import ListSettings, add_set_argument


def add_run_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=output_folder, required=True, help="run folder; finished stages in it are reused")
    add_run_arguments(parser)
    parser.add_argument("--overwrite", action="store_true", help="reuse an --out folder made from another dataset")
    add_method_arguments(parser, flags=SETTING_FLAGS)
    add_set_argument(parser)
    parser.add_argument(
        "--list-settings",
        action=ListSettings,
        help="print every research setting --set takes, with its default (under the --preset and --method given "
        "before it) and its meaning, and exit",
    )


def run_main(args) -> int:
    import time

    from matspray.memory import memory_line, process_peak_bytes
    from matspray.method.estimate import estimate_line, minutes
    from matspray.method.pipeline import Pipeline
    from matspray.predictors import NO_PREDICTOR
    from matspray.presets import asset_stage, variants_for_maps

    config = build_config_from_args(args, predictor=args.predictor, predictor_options=predictor_options_from_args(args))
    # refused before the run folder is touched; without --variant the run picks its default once its predictor is known
    variants = None if args.variant is None else variants_for_maps(args.variant, config.predictor != NO_PREDICTOR)
    with Pipeline(
        args.data, args.out, config, overwrite=args.overwrite
    ) as pipeline:  # refused while another process writes --out
        print(estimate_line(pipeline.work(variants), pipeline.device.type), flush=True)
        start = time.perf_counter()
        assets = pipeline.run_all(variants)
    timings = pipeline.run.timings()
    print(f"took {minutes(time.perf_counter() - start)}", flush=True)
    print(
        f"method {config.method}, on {pipeline.device} with rasterizer {pipeline.backend}; seconds per stage: "
        + ", ".join(f"{k} {v:.1f}" for k, v in timings.items())
    )
    print(memory_line(pipeline.run.peak_memory(), process_peak_bytes()))
    for variant in assets:
        print(f"asset [{variant}]: {pipeline.run.path(asset_stage(variant), 'asset.ply')}")
    return 0
