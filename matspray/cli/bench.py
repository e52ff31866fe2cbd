"""`matspray bench --objects N`: the method on several benchmark objects, tables averaged."""

from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--objects", type=int, default=3, help="number of objects (shapes in turn, seeds 0..N-1; default 3)")
    parser.add_argument("--preset", choices=("test", "demo", "paper"), default="demo", help="size of objects and runs (default demo)")
    parser.add_argument("--out", type=Path, help="folder for everything (default: runs/bench-PRESET)")


def run(args) -> int:
    from matspray.demo import run_bench

    out = args.out or Path("runs") / f"bench-{args.preset}"
    run_bench(out, args.objects, preset=args.preset)
    print(f"averaged tables: {out / 'tables.md'}")
    return 0
