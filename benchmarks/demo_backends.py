"""Does the demo's outcome depend on the rasterizer? `matspray demo` with backend torch and with backend numba, and
every figure of its tables (PSNR of relighting and of each material map, per variant) side by side with the
difference. The two Gaussian Splatting runs part ways after a few hundred steps (densification reacts to float
rounding), so the difference is that of two equally valid reconstructions, not rounding.

    python -m benchmarks.demo_backends [--out runs/demo-backends] [--preset demo] [--tolerance 0.1]
                                       [--refine-seed 1]
    python -m benchmarks.demo_backends --runs TORCH_RUN NUMBA_RUN [--seed-runs TORCH_RUN NUMBA_RUN]

Each demo is run into OUT/torch and OUT/numba (stages done before are reused). With --refine-seed S each backend's
demo also runs with the refinement seeded S instead (OUT/torch-refine-seedS, OUT/numba-refine-seedS: the same
geometry and lift, another equally valid refinement), and every figure's change from that seed alone is printed
beside: the spread the backends' difference is measured against. --runs / --seed-runs compare finished runs only.
Prints the table and the largest absolute difference; writes docs/results/demo-backends.json (with --results-dir,
elsewhere) for the docs' table. Exit status 1 when a difference between the backends exceeds --tolerance dB.
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


def differences(first_run: Path, second_run: Path) -> list[dict]:
    """[{variant, row, first, second, difference (second - first)}] for every figure both runs have."""
    second, first = demo_figures(second_run), demo_figures(first_run)
    return [
        {
            "variant": variant,
            "row": row,
            "first": first[variant][row],
            "second": second[variant][row],
            "difference": second[variant][row] - first[variant][row],
        }
        for variant in first
        if variant in second
        for row in first[variant]
        if row in second[variant]
    ]


def compare(torch_run: Path, numba_run: Path, seed_runs: tuple[Path, Path] | None = None) -> dict:
    """Both runs' figures and their differences (numba - torch), with the largest absolute one; with `seed_runs`
    (the same demos refined with another seed) also each figure's change from that seed alone, per backend."""
    rows = [
        {
            "variant": r["variant"],
            "row": r["row"],
            "torch": r["first"],
            "numba": r["second"],
            "difference": r["difference"],
        }
        for r in differences(torch_run, numba_run)
    ]
    result = {
        "torch_run": str(torch_run),
        "numba_run": str(numba_run),
        "rows": rows,
        "largest": max(abs(r["difference"]) for r in rows),
        "seconds": {name: _seconds(run) for name, run in (("torch", torch_run), ("numba", numba_run))},
    }
    if seed_runs is not None:
        spread = {
            backend: {(r["variant"], r["row"]): r["difference"] for r in differences(run, other)}
            for backend, run, other in zip(("torch", "numba"), (torch_run, numba_run), seed_runs)
        }
        for r in rows:
            r["seed_spread"] = {backend: spread[backend].get((r["variant"], r["row"])) for backend in spread}
        result["seed_runs"] = [str(run) for run in seed_runs]
    return result


def _seconds(run: Path) -> dict:
    path = Path(run) / "timings.json"
    return json.loads(path.read_text()) if path.exists() else {}


def comparison_lines(result: dict) -> list[str]:
    """The comparison as a markdown table: each figure with either backend, their difference and, where measured,
    its change from the refinement seed alone under each backend."""
    seeds = "seed_runs" in result
    extra = (" refinement seed alone: torch, numba |", " ---: |") if seeds else ("", "")
    lines = ["| variant | figure | torch (dB) | numba (dB) | numba - torch |" + extra[0]]
    lines.append("| --- | --- | ---: | ---: | ---: |" + extra[1])
    for r in result["rows"]:
        line = f"| {r['variant']} | {r['row']} | {r['torch']:.2f} | {r['numba']:.2f} | {r['difference']:+.2f} |"
        if seeds:
            line += " " + ", ".join(signed(r["seed_spread"][b]) for b in ("torch", "numba")) + " |"
        lines.append(line)
    return lines


def print_comparison(result: dict, tolerance: float) -> None:
    print("\n".join(comparison_lines(result)))
    verdict = "within" if result["largest"] <= tolerance else "NOT within"
    print(f"largest difference {result['largest']:.2f} dB: {verdict} {tolerance} dB")
    if "seed_runs" in result:
        print(f"largest change from the refinement seed alone: {largest_seed_spread(result):.2f} dB")


def signed(value) -> str:
    return "—" if value is None else f"{value:+.2f}"


def largest_seed_spread(result: dict) -> float:
    return max(abs(v) for r in result["rows"] for v in r["seed_spread"].values() if v is not None)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/demo-backends"))
    parser.add_argument("--preset", default="demo", choices=("test", "demo"))
    parser.add_argument("--runs", nargs=2, type=Path, metavar=("TORCH_RUN", "NUMBA_RUN"), help="compare only")
    parser.add_argument(
        "--seed-runs", nargs=2, type=Path, metavar=("TORCH_RUN", "NUMBA_RUN"), help="with --runs: the same demos "
        "refined with another seed"
    )  # fmt: skip
    parser.add_argument("--refine-seed", type=int, help="also run each backend's demo refined with this seed")
    parser.add_argument("--tolerance", type=float, default=0.1, help="dB (default 0.1)")
    parser.add_argument("--results-dir", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.seed_runs and not args.runs:
        parser.error("--seed-runs compares against --runs: give both")
    if args.runs:
        (torch_run, numba_run), seed_runs = args.runs, args.seed_runs
    else:
        from matspray.batch.demo import run_demo
        from matspray.method.config import build_config

        seeds = [(None, "")] + (
            [(args.refine_seed, f"-refine-seed{args.refine_seed}")] if args.refine_seed is not None else []
        )
        for seed, suffix in seeds:
            for backend in ("torch", "numba"):
                config = build_config(args.preset, predictor="simulated", backend=backend, refine_seed=seed)
                run_demo(args.out / f"{backend}{suffix}", preset=args.preset, config=config)
        torch_run, numba_run = args.out / "torch" / "run", args.out / "numba" / "run"
        seed_runs = (
            tuple(args.out / f"{b}{seeds[1][1]}" / "run" for b in ("torch", "numba")) if len(seeds) > 1 else None
        )
    result = compare(torch_run, numba_run, seed_runs)
    print_comparison(result, args.tolerance)
    write_json(args.results_dir / "demo-backends.json", {**result, "tolerance": args.tolerance})
    return 0 if result["largest"] <= args.tolerance else 1


if __name__ == "__main__":
    raise SystemExit(main())
