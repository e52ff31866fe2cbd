"""`matspray batch --data DATA... --out DIR`: the method once per object, as Ray tasks (local or a cluster)."""

import argparse
import sys
from pathlib import Path

from matspray.cli.options import (
    COMPUTE_FLAGS,
    add_method_arguments,
    add_run_arguments,
    build_config_from_args,
    predictor_options_from_args,
)
from matspray.cli.settings import add_set_argument


def add_parser(parser) -> None:
    parser.description = (
        "Run the whole method once per dataset folder, each object into DIR/<folder name>/ (the usual run folder), "
        "as Ray tasks: a local Ray by default, an existing cluster with --address. A rerun skips finished objects and "
        "resumes interrupted ones; an object that fails is reported and the others finish (exit status 1). "
        "DIR/summary.md and DIR/summary.json hold per-object metrics (where ground truth exists), seconds per stage "
        "and the averages. Without Ray (pip install 'matspray[cluster]'), or with --no-ray, the objects run one after "
        "another in this process."
    )
    parser.add_argument(
        "--data",
        nargs="+",
        action="extend",
        type=Path,
        metavar="DATA",
        help="dataset folders, one per object (named after the folder)",
    )
    parser.add_argument("data_positional", nargs="*", type=Path, help=argparse.SUPPRESS)  # the old `batch DATA...`
    parser.add_argument(
        "--out", type=Path, required=True, help="batch folder: DIR/<object>/ per object, DIR/summary.md"
    )
    parser.add_argument(
        "--workers",
        type=int,
        help="objects at once (default: local CPU cores / --cpus-per-object; with "
        "--address: as many as the cluster holds)",
    )
    parser.add_argument(
        "--address",
        help="join a running Ray cluster (HOST:PORT of `ray start --head`, ray://HOST:10001, or auto) "
        "instead of starting a local Ray; every machine needs matspray installed and DATA and DIR at the "
        "same paths (a shared folder)",
    )
    parser.add_argument(
        "--cpus-per-object",
        type=int,
        default=1,
        metavar="C",
        help="CPUs Ray reserves for each object, also its torch threads (default 1)",
    )
    parser.add_argument(
        "--gpus-per-object",
        type=float,
        default=0.0,
        metavar="G",
        help="GPUs Ray reserves for each object (default 0: objects run on the CPU; 0.5 puts two on one GPU)",
    )
    parser.add_argument("--no-ray", action="store_true", help=argparse.SUPPRESS)  # in the description
    add_run_arguments(parser)
    add_method_arguments(parser, visible=COMPUTE_FLAGS)
    add_set_argument(parser)


def batch_config(args):
    from matspray.batch import BatchConfig
    from matspray.predictors import NO_PREDICTOR
    from matspray.presets import variants_for_maps

    pipeline = build_config_from_args(
        args, predictor=args.predictor, predictor_options=predictor_options_from_args(args)
    )
    return BatchConfig(
        pipeline=pipeline,
        variants=None if args.variant is None else variants_for_maps(args.variant, args.predictor != NO_PREDICTOR),
        workers=args.workers,
        address=args.address,
        cpus_per_object=args.cpus_per_object,
        gpus_per_object=args.gpus_per_object,
        use_ray=not args.no_ray,
    )


def run(args) -> int:
    from matspray.batch import run_batch
    from matspray.errors import ConfigError

    datasets = [*(args.data or []), *args.data_positional]
    if not datasets:
        raise ConfigError("give the dataset folders: --data DATA [DATA ...]")
    summary = run_batch(datasets, args.out, batch_config(args))
    rows = summary["objects"]
    print(
        f"batch: {len(rows) - len(summary['failed'])} of {len(rows)} objects finished in "
        f"{summary['wall_seconds']:.0f} s "
        f"({summary['engine']})"
    )
    for failure in summary["failed"]:
        print(f"failed: {failure['name']}: {failure['error']}", file=sys.stderr)
    print(f"summary: {args.out / 'summary.md'}")
    return 1 if summary["failed"] else 0
