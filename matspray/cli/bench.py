"""`matspray bench --objects N`: the method on several benchmark objects (through `matspray batch`), tables averaged."""

import sys
from pathlib import Path

from matspray.cli.options import add_method_arguments, build_config_from_args


def add_parser(parser) -> None:
    parser.add_argument("--objects", type=int, default=3, help="number of objects (shapes in turn, seeds 0..N-1; default 3)")
    parser.add_argument("--out", type=Path, help="folder for everything (default: runs/bench-PRESET)")
    parser.add_argument("--workers", type=int, help="objects at once, as Ray tasks (default: one per CPU core; "
                        "without Ray installed, one after another)")
    add_method_arguments(parser)


def run(args) -> int:
    from matspray.demo import run_bench

    out = args.out or Path("runs") / f"bench-{args.preset}"
    summary = run_bench(out, args.objects, preset=args.preset, config=build_config_from_args(args, predictor="simulated"),
                        workers=args.workers)
    for failure in summary["failed"]:
        print(f"failed: {failure['name']}: {failure['error']}", file=sys.stderr)
    if summary["averages"] is not None:
        print(f"averaged tables: {out / 'tables.md'}")
    print(f"per object: {out / 'summary.md'}")
    return 1 if summary["failed"] else 0
