"""Which prediction batches the Neural Merger trusts, against what the simulated predictor did to them.

    python -m benchmarks.merger_batches RUN [RUN ...]

For every run folder with a `full` asset (its merger.pt) and a simulated predictor (materials2d/predictor.json
lists each batch's drawn errors): per batch of views, the drawn exposure, baked-shading exponent, roughness offset
and spurious metallic, and the share of the merger's weight that batch gets, per channel group (base colour,
roughness, metallic), as a ratio to its share under equal weights over the views that saw each Gaussian
(1: as the projection average; above 1: trusted more). The last lines pool the batches with and without spurious
metallic: a merger that prefers wrong batches shows ratios above 1 for them.

`benchmarks.ceilings` keeps `full` refined under the true training light in OBJECT/runs/MODEL-true-light; pass that
folder too to see how the choice changes when the light is known.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from benchmarks.generalise_tables import fmt
from matspray.errors import MatsprayError, file_error
from matspray.material import GROUPS

GROUP_NAMES = tuple(GROUPS)


def merger_weights(run: Path) -> tuple[dict[str, torch.Tensor], torch.Tensor, list[str]]:
    """The full asset's merger weights {group: [N, V]}, the seen mask [N, V] and the lifted views' names."""
    from matspray.method.asset import read_asset
    from matspray.method.lift import load_lift
    from matspray.method.merger import load_merger

    for needed in (run / "asset" / "merger.pt", run / "lift" / "projected.pt"):
        if not needed.exists():
            raise file_error(needed, "is missing", "run the full variant first (matspray run --variant full)")
    lift = load_lift(run / "lift" / "projected.pt", "cpu")
    asset = read_asset(run / "asset")
    merger = load_merger(
        run / "asset" / "merger.pt", lift.values.shape[1], torch.zeros(2, 3)
    )  # bounds come from the checkpoint
    with torch.no_grad():
        _, weights = merger(asset.gaussians.means, lift.values, lift.seen, return_weights=True)
    return weights, lift.seen, list(lift.view_names)


def batch_shares(
    weights: dict[str, torch.Tensor], seen: torch.Tensor, views: list[str], batches: list[dict]
) -> list[dict]:
    """Per batch: its drawn errors and, per group, the mean over Gaussians of the weight on the batch's views
    divided by the same mean under equal weights over the seen views (None where no Gaussian saw the batch)."""
    equal = seen.float() / seen.sum(1, keepdim=True).clamp_min(1)  # [N, V]
    rows = []
    for batch in batches:
        index = [views.index(v) for v in batch["views"] if v in views]
        uniform = float(equal[:, index].sum(1).mean()) if index else 0.0
        ratios = {g: (float(w[:, index].sum(1).mean()) / uniform if uniform > 0 else None) for g, w in weights.items()}
        rows.append(
            {
                "views": len(index),
                "exposure": batch["exposure"],
                "shading": batch["shading"],
                "roughness_offset": batch["roughness_offset"],
                "spurious_metallic": batch["spurious_metallic"],
                "uniform": uniform,
                "ratio": ratios,
            }
        )
    return rows


def pooled(rows: list[dict], with_metallic: bool) -> dict:
    """The weight ratio of the batches with (or without) spurious metallic taken together, per group."""
    chosen = [r for r in rows if (r["spurious_metallic"] > 0) == with_metallic and r["uniform"] > 0]
    uniform = sum(r["uniform"] for r in chosen)
    return {
        g: (sum(r["ratio"][g] * r["uniform"] for r in chosen) / uniform if uniform > 0 else None) for g in GROUP_NAMES
    }


def read_batches(run: Path) -> list[dict]:
    path = run / "materials2d" / "predictor.json"
    try:
        described = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise file_error(path, f"cannot be read: {exc}") from None
    if not described.get("batches"):
        raise file_error(path, "lists no batches", "only a simulated predictor records the errors it drew")
    return described["batches"]


def report(run: Path) -> list[str]:
    weights, seen, views = merger_weights(run)
    rows = batch_shares(weights, seen, views, read_batches(run))
    lines = [
        f"{run}",
        "| batch | views | exposure | shading | rough offset | spurious metal | "
        + " | ".join(f"w {g} / equal" for g in GROUP_NAMES)
        + " |",
        "|---" * (6 + len(GROUP_NAMES)) + "|",
    ]
    for number, r in enumerate(rows):
        lines.append(
            f"| {number} | {r['views']} | {r['exposure']:.2f} | {r['shading']:.2f} | {r['roughness_offset']:+.2f} | "
            f"{r['spurious_metallic']:.2f} | " + " | ".join(fmt(r["ratio"][g]) for g in GROUP_NAMES) + " |"
        )
    for label, flag in (("with spurious metallic", True), ("without", False)):
        share = pooled(rows, flag)
        lines.append(f"- batches {label}: " + ", ".join(f"{g} {fmt(share[g])}" for g in GROUP_NAMES))
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.merger_batches",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "runs", nargs="+", type=Path, metavar="RUN", help="run folders with a full asset and a simulated predictor"
    )
    args = parser.parse_args(argv)
    try:
        for run in args.runs:
            print("\n".join(report(run)) + "\n")
    except MatsprayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
