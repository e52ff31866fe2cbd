"""`matspray demo`: a benchmark object, the method and its ablations, evaluation and the report."""

from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--preset", choices=("test", "demo"), default="demo",
                        help="demo: 128 px, 40 views, under 15 minutes on 2 CPU cores (default); test: tiny, under 3 minutes")
    parser.add_argument("--out", type=Path, help="folder for the object, the run and the report (default: runs/demo-PRESET)")
    parser.add_argument("--shape", default="composite", help="shape of the benchmark object (default: composite)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the object's materials (default 0)")


def run(args) -> int:
    import time

    from matspray.demo import run_demo

    start = time.perf_counter()
    report = run_demo(args.out or Path("runs") / f"demo-{args.preset}", preset=args.preset, shape=args.shape, seed=args.seed)
    print(f"demo finished in {time.perf_counter() - start:.0f} s")
    print(f"tables: {report.parent / 'eval' / 'tables.md'}")
    print(f"report: {report}")
    return 0
