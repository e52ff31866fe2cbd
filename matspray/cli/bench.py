"""`matspray bench --objects N`: the method on several benchmark objects, tables averaged."""

from pathlib import Path

from matspray.cli.options import add_method_arguments, build_config_from_args


def add_parser(parser) -> None:
    parser.add_argument("--objects", type=int, default=3, help="number of objects (shapes in turn, seeds 0..N-1; default 3)")
    parser.add_argument("--out", type=Path, help="folder for everything (default: runs/bench-PRESET)")
    add_method_arguments(parser)


def run(args) -> int:
    from matspray.demo import run_bench

    out = args.out or Path("runs") / f"bench-{args.preset}"
    run_bench(out, args.objects, preset=args.preset, config=build_config_from_args(args, predictor="simulated"))
    print(f"averaged tables: {out / 'tables.md'}")
    return 0
