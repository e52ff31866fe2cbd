"""`matspray eval --run RUN [--data DATA]`: metrics, the paper's tables and the HTML report."""

import os
from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--run", type=Path, required=True, help="run folder made by `matspray run`")
    parser.add_argument("--data", type=Path, help="the run's dataset (default: the folder the run was made from)")
    parser.add_argument("--lpips-weights", type=Path, default=os.environ.get("MATSPRAY_LPIPS_WEIGHTS"),
                        help="LPIPS v0.1 AlexNet weights (.npz); default: $MATSPRAY_LPIPS_WEIGHTS or ../shared/data/lpips")
    parser.add_argument("--aligned", action="store_true", help="also report base color and relighting after per-channel scale alignment")
    parser.add_argument("--no-report", action="store_true", help="skip report.html")


def run(args) -> int:
    from matspray.device import configure_threads

    configure_threads()
    from matspray.eval.report import write_report
    from matspray.eval.run_eval import evaluate_run

    metrics = evaluate_run(args.run, args.data, lpips_weights=args.lpips_weights, aligned=args.aligned)
    print((args.run / "eval" / "tables.md").read_text())
    if not args.no_report:
        print(f"report: {write_report(args.run, metrics, args.data)}")
    return 0
