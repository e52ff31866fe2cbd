"""The commands of many runs, over `matspray.batch`: `demo` (a benchmark object, the method and its ablations,
evaluation and the report), `bench` (the demo over several objects, through `batch`, tables averaged) and `batch` (the
method once per object, as Ray tasks on this machine or a cluster)."""

import argparse
import sys
from pathlib import Path

from matspray.cli.options import (
    add_method_arguments,
    add_run_arguments,
    build_config_from_args,
    output_folder,
    predictor_options_from_args,
)
from matspray.cli.settings import add_set_argument


# `matspray demo`: a benchmark object, the method and its ablations, evaluation and the report
def add_demo_parser(parser) -> None:
    parser.add_argument(
        "--out",
        type=output_folder,
        help="folder for the object, the run and the report (default: runs/demo-PRESET, "
        "runs/demo-PRESET-paper for --method paper)",
    )
    parser.add_argument("--shape", default="composite", help="shape of the benchmark object (default: composite)")
    parser.add_argument(
        "--object-seed", type=int, default=0, help="seed of the object's shape and materials (default 0)"
    )
    add_method_arguments(parser)
    add_set_argument(parser, "geometry.iterations=1000 refine.iterations=200")


def demo_main(args) -> int:
    import time

    from matspray.batch.demo import run_demo

    config = build_config_from_args(args, predictor="simulated")
    refuse_paper_on_a_cpu(args.preset, config.device)
    start = time.perf_counter()
    default_out = Path("runs") / (f"demo-{args.preset}" + ("" if args.method == "matspray" else f"-{args.method}"))
    report = run_demo(
        args.out or default_out, preset=args.preset, shape=args.shape, seed=args.object_seed, config=config
    )
    print(f"demo ({config.method}) finished in {time.perf_counter() - start:.0f} s")
    print(f"tables: {report.parent / 'eval' / 'tables.md'}")
    print(f"report: {report}")
    return 0


def refuse_paper_on_a_cpu(preset: str, device: str) -> None:
    """The paper preset (a 512 px object of 100 + 200 views, 30 000 Gaussian Splatting steps) is sized for one CUDA GPU;
    on a machine without one it would run for many hours, so it runs there only when --device cpu asks for it."""
    from matspray.device import resolve_device
    from matspray.errors import SettingError

    if preset == "paper" and device == "auto" and resolve_device(device).type == "cpu":
        raise SettingError(
            "preset",
            "paper is sized for one CUDA GPU (512 px, 100 training and 200 test views, 30 000 steps) and this "
            "machine has none: many hours here. Use --preset demo, or add --device cpu to run it here anyway",
        )


# `matspray bench --objects N` or `--assets PATH...`: the method on several benchmark objects (through
# `matspray batch`), tables averaged
def add_bench_parser(parser) -> None:
    parser.add_argument(
        "--objects",
        type=int,
        default=None,
        help="number of procedural objects (shapes in turn, seeds 0..N-1; default 3)",
    )
    parser.add_argument(
        "--assets",
        nargs="+",
        type=Path,
        default=None,
        metavar="PATH",
        help="glTF 2.0 files (.glb/.gltf) or folders of them: one benchmark object each (`synth --asset`), "
        "instead of procedural ones",
    )
    parser.add_argument(
        "--out",
        type=output_folder,
        help="folder for everything (default: runs/bench-PRESET, with --assets runs/bench-assets-PRESET)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        help="objects at once, as Ray tasks (default: one per CPU core; without Ray installed, one after another)",
    )
    add_method_arguments(parser)
    add_set_argument(parser)


def bench_main(args) -> int:
    from matspray.batch.demo import asset_objects, check_assets, run_bench
    from matspray.errors import ConfigError

    if args.assets is not None and args.objects is not None:
        raise ConfigError("--objects and --assets exclude each other; give one")
    objects = asset_objects(args.assets) if args.assets is not None else (3 if args.objects is None else args.objects)
    if args.assets is not None:
        check_assets(objects)
    out = args.out or Path("runs") / (
        f"bench-assets-{args.preset}" if args.assets is not None else f"bench-{args.preset}"
    )
    summary = run_bench(
        out,
        objects,
        preset=args.preset,
        config=build_config_from_args(args, predictor="simulated"),
        workers=args.workers,
    )
    for failure in summary["failed"]:
        print(f"failed: {failure['name']}: {failure['error']}", file=sys.stderr)
    if summary["averages"] is not None:
        print(f"averaged tables: {out / 'tables.md'}")
    print(f"per object: {out / 'summary.md'}")
    return 1 if summary["failed"] else 0


# `matspray batch --data DATA... --out DIR`: the method once per object, as Ray tasks (local or a cluster)
def add_batch_parser(parser) -> None:
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
        "--out", type=output_folder, required=True, help="batch folder: DIR/<object>/ per object, DIR/summary.md"
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
    add_method_arguments(parser)
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


def batch_main(args) -> int:
    from matspray.batch import run_batch
    from matspray.errors import ConfigError

    datasets = [*(args.data or []), *args.data_positional]
    if not datasets:
        raise ConfigError("give the dataset folders: --data DATA [DATA ...]")
    missing = [str(path) for path in datasets if not Path(path).is_dir()]
    if missing:  # said before any worker starts; a dataset that is there but broken fails as its object
        raise ConfigError(f"--data: {', '.join(missing)}: not a folder (give each object's dataset folder)")
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
