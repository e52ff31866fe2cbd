"""Does the demo's outcome depend on the rasterizer? `matspray demo` with backend torch and with backend numba, and
every figure of its tables (PSNR of relighting and of each material map, per variant) side by side with the
difference. The two Gaussian Splatting runs part ways after a few hundred steps (densification reacts to float
rounding), so the difference is that of two equally valid reconstructions, not rounding.

    python -m benchmarks.demo_backends [--out runs/demo-backends] [--preset demo] [--tolerance 0.1]
    python -m benchmarks.demo_backends --runs TORCH_RUN NUMBA_RUN     # compare two finished demo runs only

Each demo is run into OUT/torch and OUT/numba (stages done before are reused). Prints the table and the largest
absolute difference; writes docs/results/demo-backends.json (with --results-dir, elsewhere) for the docs' table.
Exit status 1 when a difference exceeds --tolerance dB.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from matspray.files import write_json

ROWS = ("relighting", "basecolor", "roughness", "metallic")
RESULTS = Path("docs/results")


def demo_figures(run: Path) -> dict[str, dict[str, float]]:
    """{variant: {row: PSNR}} of a finished demo run's evaluation (eval/metrics.json)."""
    metrics = json.loads((Path(run) / "eval" / "metrics.json").read_text())
    return {
        variant: {row: entry["summary"][row]["psnr"] for row in ROWS if row in entry["summary"]}
        for variant, entry in metrics["variants"].items()
    }


def compare(torch_run: Path, numba_run: Path) -> dict:
    """Both runs' figures and their differences (numba - torch), with the largest absolute one."""
    ours, reference = demo_figures(numba_run), demo_figures(torch_run)
    rows = [
        {
            "variant": variant,
            "row": row,
            "torch": reference[variant][row],
            "numba": ours[variant][row],
            "difference": ours[variant][row] - reference[variant][row],
        }
        for variant in reference
        if variant in ours
        for row in reference[variant]
        if row in ours[variant]
    ]
    return {
        "torch_run": str(torch_run),
        "numba_run": str(numba_run),
        "rows": rows,
        "largest": max(abs(r["difference"]) for r in rows),
        "seconds": {name: _seconds(run) for name, run in (("torch", torch_run), ("numba", numba_run))},
    }


def _seconds(run: Path) -> dict:
    path = Path(run) / "timings.json"
    return json.loads(path.read_text()) if path.exists() else {}


def print_comparison(result: dict, tolerance: float) -> None:
    print("| variant | figure | torch (dB) | numba (dB) | numba - torch |")
    print("| --- | --- | ---: | ---: | ---: |")
    for r in result["rows"]:
        print(f"| {r['variant']} | {r['row']} | {r['torch']:.2f} | {r['numba']:.2f} | {r['difference']:+.2f} |")
    verdict = "within" if result["largest"] <= tolerance else "NOT within"
    print(f"largest difference {result['largest']:.2f} dB: {verdict} {tolerance} dB")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/demo-backends"))
    parser.add_argument("--preset", default="demo", choices=("test", "demo"))
    parser.add_argument("--runs", nargs=2, type=Path, metavar=("TORCH_RUN", "NUMBA_RUN"), help="compare only")
    parser.add_argument("--tolerance", type=float, default=0.1, help="dB (default 0.1)")
    parser.add_argument("--results-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.runs:
        torch_run, numba_run = args.runs
    else:
        from matspray.config import build_config
        from matspray.demo import run_demo

        for backend in ("torch", "numba"):
            config = build_config(args.preset, predictor="simulated", backend=backend)
            run_demo(args.out / backend, preset=args.preset, config=config)
        torch_run, numba_run = args.out / "torch" / "run", args.out / "numba" / "run"
    result = compare(torch_run, numba_run)
    print_comparison(result, args.tolerance)
    write_json(args.results_dir / "demo-backends.json", {**result, "tolerance": args.tolerance})
    return 0 if result["largest"] <= args.tolerance else 1


if __name__ == "__main__":
    raise SystemExit(main())
