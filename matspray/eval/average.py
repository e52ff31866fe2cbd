"""Averages over objects: the paper reports every table as the mean over its benchmark objects."""

from __future__ import annotations

import math

from matspray.eval.tables import UNION


def mean_or_none(values) -> float | None:
    """The mean of the values that are not None; None when there are none."""
    values = [v for v in values if v is not None]
    if not values:
        return None
    return math.fsum(values) / len(values)


def average_tables(metrics: list[dict]) -> dict:
    """Average the per-object table entries (eval/metrics.json of each object); metallic PSNR follows
    the paper's infinity rule (objects with infinite PSNR are counted and left out of the mean), under
    the object mask (GT) and the silhouette-counting union ("metallic_union") alike. Every row of
    table1, "<row>_union" included, is averaged; a row averages only the objects that have it."""
    out: dict = {
        "notes": sorted({n for m in metrics for n in m.get("notes", [])}),
        "lpips": metrics[0].get("lpips") if metrics else None,
    }
    for key in ("table2", "softmax", "table2" + UNION, "softmax" + UNION):  # UNION: the silhouette-counting figures
        names = {name for m in metrics for name in m.get(key, {})}
        if not names and key.endswith(UNION):
            continue  # only older metrics.json files: no union tables at all rather than empty ones
        out[key] = {
            name: {
                metric: mean_or_none([m[key][name].get(metric) for m in metrics if name in m.get(key, {})])
                for metric in ("psnr", "ssim", "lpips")
            }
            for name in names
        }
    table1 = {}
    for method in {name for m in metrics for name in m.get("table1", {})}:
        rows = {}
        for row in {r for m in metrics for r in m.get("table1", {}).get(method, {})}:
            entries = [m["table1"][method][row] for m in metrics if row in m.get("table1", {}).get(method, {})]
            if row in ("metallic", "metallic" + UNION):
                finite = [e["psnr"] for e in entries if e.get("psnr") is not None and math.isfinite(e["psnr"])]
                rows[row] = {
                    "psnr": mean_or_none(finite) if finite else math.inf,
                    "ssim": mean_or_none([e.get("ssim") for e in entries]),
                    "lpips": mean_or_none([e.get("lpips") for e in entries]),
                    "psnr_infinite": len(entries) - len(finite),
                    "objects": len(entries),
                }
            else:
                rows[row] = {
                    metric: mean_or_none([e.get(metric) for e in entries]) for metric in ("psnr", "ssim", "lpips")
                }
        table1[method] = rows
    out["table1"] = table1
    stages = {stage for m in metrics for column in m.get("timings", {}).values() for stage in column}
    out["timings"] = {
        "Ours (mean per object)": {
            s: mean_or_none([c.get(s) for m in metrics for c in m.get("timings", {}).values()]) for s in stages
        }
    }
    return out
