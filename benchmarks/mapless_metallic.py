"""How metallic the variants without 2D maps make their objects: no-prior (the paper's baseline) and photos-only (the
user's default, by its `refine.metallic_prior_weight` and `refine.metallic_prior_start`).

    python -m benchmarks.generalise --set dev --objects 3 --preset test --models ground-truth \
        --variants no-prior photos-only --out DIR
    python -m benchmarks.generalise --set dev --objects 3 --preset test --models ground-truth --variants photos-only \
        --refine metallic_prior_weight=W metallic_prior_start=S --tag wW-sS --out DIR     # once per (W, S)
    python -m benchmarks.mapless_metallic DIR

Reads every run the generalise passes left in DIR (DIR/objects/OBJECT/runs/RUN with an asset-no-prior or
asset-photos-only, evaluated) and prints, per object and configuration (variant, refinement steps, weight, start: as
the asset's stage record says it was refined), the asset's mean metallic and the share of its Gaussians above 0.5,
beside the mean of the object's true metallic over its test views' masks, and the run's relighting and metallic PSNR
(its eval/metrics.json: test views, object mask); then the mean of each configuration over the objects that have it.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from matspray.data.images import read_image, read_raw
from matspray.method.asset import read_asset
from matspray.presets import MAPLESS, asset_stage

GREY = 0.5  # where a free source's metallic starts without `metallic_prior_start` (and in stage records before it)


def true_metallic(data: Path) -> float | None:
    """The mean true metallic over the test views' masks (their `*_metallic.png` maps beside the renders, linear)."""
    total = count = 0.0
    for path in sorted((data / "test").glob("*_metallic.png")):
        values = read_raw(path)[..., 0]
        _, alpha = read_image(path.with_name(path.name.replace("_metallic", "")))
        inside = alpha > 0.5 if alpha is not None else values >= 0
        total, count = total + float(values[inside].sum()), count + float(inside.sum())
    return total / count if count else None


def configuration(stage: Path, variant: str) -> tuple:
    """(variant, steps, weight, start) of an asset as its stage record says it was refined."""
    settings = json.loads((stage / "stage.json").read_text())["settings"]
    weight = settings.get("metallic_prior_weight", 0.0)
    return variant, settings["iterations"], weight, settings.get("metallic_prior_start", GREY)


def psnr(metrics: dict, variant: str, row: str) -> float | None:
    return metrics.get("variants", {}).get(variant, {}).get("summary", {}).get(row, {}).get("psnr")


def asset_rows(run: Path) -> list[tuple[tuple, dict]]:
    """(configuration, figures) of each evaluated asset without maps in one run folder."""
    path = run / "eval" / "metrics.json"
    metrics = json.loads(path.read_text()) if path.is_file() else {}
    rows = []
    for variant in MAPLESS:
        stage = run / asset_stage(variant)
        if (stage / "asset.ply").is_file() and variant in metrics.get("variants", {}):
            metallic = read_asset(stage).materials[:, 4]
            figures = {
                "mean": float(metallic.mean()),
                "above": float((metallic > 0.5).float().mean()),
                "relight": psnr(metrics, variant, "relighting"),
                "metal": psnr(metrics, variant, "metallic"),
            }
            rows.append((configuration(stage, variant), figures))
    return rows


def fmt(value: float | None, digits: int = 2) -> str:
    return "—" if value is None or math.isinf(value) else f"{value:.{digits}f}"


def row(lead: str, truth: str, config: tuple, f: dict) -> str:
    variant, steps, weight, start = config
    cells = [lead, truth, variant, str(steps), f"{weight:g}", f"{start:g}", fmt(f["mean"], 3)]
    cells += [f"{100 * f['above']:.0f} %", fmt(f["relight"]), fmt(f["metal"])]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="the --out folder of the generalise passes")
    args = parser.parse_args(argv)
    head = "object | true metallic | variant | steps | weight | start | mean metallic | Gaussians > 0.5 | relight"
    head += " | metal"
    print(f"| {head} |\n|" + "---|" * len(head.split("|")))
    by_config: dict[tuple, list[dict]] = {}
    for obj in sorted((args.out / "objects").iterdir()):
        truth = true_metallic(obj / "data")
        rows = {config: f for run in sorted((obj / "runs").iterdir()) for config, f in asset_rows(run)}
        for config in sorted(rows):
            print(row(obj.name, "—" if truth is None else f"{truth:.3f}", config, rows[config]))
            by_config.setdefault(config, []).append(rows[config])
    objects = max((len(v) for v in by_config.values()), default=0)
    for config, figures in sorted(by_config.items()):
        if len(figures) == objects:  # a configuration some object lacks would not be comparable
            mean = {k: mean_of([f[k] for f in figures]) for k in figures[0]}
            print(row(f"mean of {objects}", "", config, mean))
    return 0


def mean_of(values: list) -> float | None:
    finite = [v for v in values if v is not None]
    return math.fsum(finite) / len(finite) if len(finite) == len(values) else None


if __name__ == "__main__":
    raise SystemExit(main())
