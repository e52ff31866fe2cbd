"""`matspray demo`: a benchmark object, the method and its ablations, evaluation and the report."""

from pathlib import Path

from matspray.cli.options import add_method_arguments, build_config_from_args


def add_parser(parser) -> None:
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for the object, the run and the report (default: runs/demo-PRESET, "
        "runs/demo-PRESET-paper for --method paper)",
    )
    parser.add_argument("--shape", default="composite", help="shape of the benchmark object (default: composite)")
    parser.add_argument(
        "--object-seed", type=int, default=0, help="seed of the object's shape and materials (default 0)"
    )
    add_method_arguments(parser, presets=("test", "demo"))


def run(args) -> int:
    import time

    from matspray.demo import run_demo

    config = build_config_from_args(args, predictor="simulated")
    start = time.perf_counter()
    default_out = Path("runs") / (f"demo-{args.preset}" + ("" if args.method == "matspray" else f"-{args.method}"))
    report = run_demo(
        args.out or default_out, preset=args.preset, shape=args.shape, seed=args.object_seed, config=config
    )
    print(f"demo ({config.method}) finished in {time.perf_counter() - start:.0f} s")
    print(f"tables: {report.parent / 'eval' / 'tables.md'}")
    print(f"report: {report}")
    return 0
