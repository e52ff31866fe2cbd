"""The paper's tables as markdown, from plain dicts (the content of eval/metrics.json).

Cell conventions: an entry that is absent prints '—' (not measured / run not made); a metric that is
present but None prints 'n/a' (LPIPS unavailable); an infinite PSNR prints '∞'. The metallic PSNR
follows the paper: with k > 0 objects at infinite PSNR it prints '∞*/<mean of the others>' and a
footnote gives k. Where two or more columns hold numbers, the best of a row is bold.

Input shapes (every level optional):
  table1:  {method: {row: {"psnr": x, "ssim": x, "lpips": x}}}, rows "relighting", "basecolor",
           "roughness", "metallic" (also "psnr_infinite": k, "objects": n), and the scale-aligned
           "relighting_aligned", "basecolor_aligned"; each optionally also as "<row>_union", the
           object + silhouette (union) figure, printed right below its object-mask (GT) row
  table2 / softmax (and table2_union / softmax_union):  {variant: {"psnr": x, "ssim": x, "lpips": x}}
  timings: {column: {stage: seconds}}
  objects: {name: {"source": str, "psnr": {"relighting"|"basecolor": {variant: x}},
           "seconds": {"synth": s, "method": s}}}
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Mapping, Sequence

from matspray.data.images import atomic_target
from matspray.presets import ABLATION, LABELS, SOFTMAX_ABLATION

MISSING = "—"
UNAVAILABLE = "n/a"
METRIC_HEADERS = {"psnr": "PSNR ↑", "ssim": "SSIM ↑", "lpips": "LPIPS ↓"}
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False}
TABLE1_ROWS = {
    "relighting": "Relighting",
    "basecolor": "BaseColor",
    "roughness": "Roughness",
    "metallic": "Metallic",
}
ALIGNED_ROWS = {
    "relighting_aligned": "Relighting (scale-aligned)",
    "basecolor_aligned": "BaseColor (scale-aligned)",
}
UNION = "_union"  # key suffix of every silhouette-counting figure ("relighting" -> "relighting_union")
UNION_LABEL = "object + silhouette (union)"
ABLATION_VARIANTS = tuple(LABELS[v] for v in ABLATION)
SOFTMAX_VARIANTS = tuple(LABELS[v] for v in SOFTMAX_ABLATION)
STAGE_LABELS = {
    "predict": "Diffusion predictions",
    "geometry": "Gaussian Splatting",
    "normals": "Normal generation",
    "lift": "Projection (ray tracing)",
    "visibility": "Shadow maps (visibility)",
    "refine": "Material optimization",
}
ALIGNED_NOTE = (
    "Scale-aligned rows: the prediction is multiplied per channel by the median ratio "
    "ground truth / prediction over object pixels (NeRFactor/TensoIR convention) before "
    "compositing; they are not comparable with the unaligned rows or the paper."
)
UNION_NOTE = (
    "Rows without a suffix: object mask (GT): prediction and truth both composited with the ground-truth "
    "mask, full image, so nothing at or outside the true silhouette counts (the paper's convention). Rows "
    f"marked '{UNION_LABEL}': each composited with its own alpha (the truth with its mask), scored over the "
    "union of the two silhouettes (weights max(alpha, mask); LPIPS on the union's bounding box), so extra "
    "and missing silhouette counts; the two are on different regions, compare like with like."
)


# ------------------------------------------------------------------------------------------ cells
def format_number(value: float, decimals: int = 3) -> str:
    if math.isinf(value):
        return "∞" if value > 0 else "-∞"
    return f"{value:.{decimals}f}"


def format_metric(entry: Mapping | None, metric: str) -> str:
    """One cell: '—' when absent, 'n/a' when None, else the number."""
    if entry is None or metric not in entry:
        return MISSING
    value = entry[metric]
    return UNAVAILABLE if value is None else format_number(float(value))


def format_metallic_psnr(entry: Mapping | None) -> str:
    """The paper's metallic PSNR cell: '∞*/27.202' when some objects are at infinite PSNR."""
    infinite = int((entry or {}).get("psnr_infinite", 0))
    if infinite == 0:
        return format_metric(entry, "psnr")
    mean = entry.get("psnr")
    return "∞*" if mean is None else f"∞*/{format_number(float(mean))}"


def _comparable(entry: Mapping | None, metric: str) -> float | None:
    if entry is None or entry.get(metric) is None:
        return None
    if metric == "psnr" and int(entry.get("psnr_infinite", 0)) > 0:
        return None  # '∞*/x' is not one number
    return float(entry[metric])


def _bold_best(cells: list[str], values: list[float | None], higher_is_better: bool) -> list[str]:
    numbers = [v for v in values if v is not None]
    if len(numbers) < 2:
        return cells
    best = max(numbers) if higher_is_better else min(numbers)
    return [f"**{cell}**" if value == best else cell for cell, value in zip(cells, values)]


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub markdown table; the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join([":---"] + ["---:"] * (len(header) - 1)) + " |"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ tables
def material_table(methods: Mapping[str, Mapping[str, Mapping]]) -> str:
    """Table 1: rows Relighting/BaseColor/Roughness/Metallic (+ scale-aligned), PSNR/SSIM/LPIPS per method."""
    names = list(methods)
    metrics = list(METRIC_HEADERS)
    header = ["Task"] + [
        METRIC_HEADERS[m] if len(names) == 1 else f"{name} {METRIC_HEADERS[m]}" for name in names for m in metrics
    ]
    present_aligned = [key for key in ALIGNED_ROWS if any(key in methods[name] for name in names)]
    row_labels = {}
    for key, label in {**TABLE1_ROWS, **{key: ALIGNED_ROWS[key] for key in present_aligned}}.items():
        row_labels[key] = label
        if any(key + UNION in methods[name] for name in names):  # the silhouette-counting figure right below
            row_labels[key + UNION] = f"{label}, {UNION_LABEL}"
    rows = []
    for key, label in row_labels.items():
        columns = {}
        for metric in metrics:
            entries = [methods[name].get(key) for name in names]
            if key in ("metallic", "metallic" + UNION) and metric == "psnr":
                cells = [format_metallic_psnr(entry) for entry in entries]
            else:
                cells = [format_metric(entry, metric) for entry in entries]
            values = [_comparable(entry, metric) for entry in entries]
            columns[metric] = _bold_best(cells, values, HIGHER_IS_BETTER[metric])
        rows.append([label] + [columns[m][i] for i in range(len(names)) for m in metrics])
    notes = []
    for key, why in (
        ("metallic", "are non-metallic and predicted all zero"),
        ("metallic" + UNION, "have exact metallic maps and silhouettes"),
    ):
        for name in names:
            metallic = methods[name].get(key) or {}
            infinite = int(metallic.get("psnr_infinite", 0))
            if infinite:
                of = f" of {metallic['objects']}" if "objects" in metallic else ""
                who = f"{name}: " if len(names) > 1 else ""
                where = f"Metallic, {UNION_LABEL}: " if key.endswith(UNION) else ""
                notes.append(
                    f"\\* {where}{who}{infinite}{of} objects {why}, so their "
                    "metallic PSNR is infinite; they are left out of the average after the slash."
                )
    if present_aligned:
        notes.append(ALIGNED_NOTE)
    if any(key.endswith(UNION) for key in row_labels):
        notes.append(UNION_NOTE)
    return "\n\n".join([markdown_table(header, rows)] + notes)


def variant_table(variants: Mapping[str, Mapping], order: Sequence[str] = ()) -> str:
    """Rows of PSNR/SSIM/LPIPS per variant: the names in `order` first ('—' when that run is
    missing), then any other variants in their given order."""
    names = list(order) + [name for name in variants if name not in order]
    metrics = list(METRIC_HEADERS)
    columns = {}
    for metric in metrics:
        entries = [variants.get(name) for name in names]
        cells = [format_metric(entry, metric) for entry in entries]
        columns[metric] = _bold_best(cells, [_comparable(e, metric) for e in entries], HIGHER_IS_BETTER[metric])
    rows = [[name] + [columns[m][i] for m in metrics] for i, name in enumerate(names)]
    return markdown_table(["Method"] + [METRIC_HEADERS[m] for m in metrics], rows)


def ablation_table(variants: Mapping[str, Mapping]) -> str:
    """Table 2: Full / Supervised / Proj. Average."""
    return variant_table(variants, ABLATION_VARIANTS)


def softmax_table(variants: Mapping[str, Mapping]) -> str:
    """The supplementary softmax ablation: Full / Without Softmax."""
    return variant_table(variants, SOFTMAX_VARIANTS)


def timings_table(columns: Mapping[str, Mapping[str, float | None]]) -> str:
    """Table 3: seconds per stage per column (e.g. one run, or one device) and their total.

    Known stages (predict, geometry, normals, lift, refine) come first with the paper's labels;
    other stages follow under their own names. The total sums the numbers shown in the column.
    """
    names = list(columns)
    stages = [s for s in STAGE_LABELS if any(s in columns[n] for n in names)]
    stages += [s for n in names for s in columns[n] if s not in stages]
    stages = list(dict.fromkeys(stages))
    rows = [[STAGE_LABELS.get(s, s)] + [_seconds(columns[name].get(s)) for name in names] for s in stages]
    totals = []
    for name in names:
        numbers = [float(v) for v in columns[name].values() if v is not None]
        totals.append(f"**{_seconds(sum(numbers))}**" if numbers else MISSING)
    rows.append(["**Total**"] + totals)
    return markdown_table(["Stage"] + [f"{name} (s)" for name in names], rows)


def objects_table(objects: Mapping[str, Mapping]) -> str:
    """A benchmark's objects: relighting PSNR of each variant (the best bold), the order of the variants,
    base colour PSNR of Full, and seconds; then how often Full beats each other variant."""
    variants = list(dict.fromkeys(ABLATION_VARIANTS + SOFTMAX_VARIANTS))
    variants += [v for row in objects.values() for v in row["psnr"].get("relighting", {}) if v not in variants]
    rows, wins = [], {v: [0, 0] for v in variants[1:]}
    for name, row in objects.items():
        relit = row["psnr"].get("relighting", {})
        values = [relit.get(v) for v in variants]
        cells = _bold_best([MISSING if x is None else format_number(x, 2) for x in values], values, True)
        order = " > ".join(sorted((v for v in variants if relit.get(v) is not None), key=lambda v: -relit[v]))
        base = row["psnr"].get("basecolor", {}).get("Full")
        seconds = row.get("seconds", {})
        rows.append(
            [f"{name} ({row.get('source', '')})"]
            + cells
            + [
                order,
                MISSING if base is None else format_number(base, 2),
                _seconds(seconds.get("synth")),
                _seconds(seconds.get("method")),
            ]
        )
        for other in wins:
            if relit.get("Full") is not None and relit.get(other) is not None:
                wins[other][0] += relit["Full"] > relit[other]
                wins[other][1] += 1
    header = (
        ["Object"]
        + [f"{v} relit PSNR" for v in variants]
        + ["order", "Full base colour PSNR", "synth (s)", "stages (s)"]
    )
    lines = [f"Full > {other} (relighting PSNR) on {k} of {n} objects" for other, (k, n) in wins.items() if n]
    return "\n\n".join([markdown_table(header, rows)] + (["\n".join(f"- {line}" for line in lines)] if lines else []))


def _seconds(value: float | None) -> str:
    return MISSING if value is None else f"{float(value):.1f}"


# ------------------------------------------------------------------------------------------ document
def tables_markdown(metrics: Mapping) -> str:
    """eval/tables.md: a title, notes, the LPIPS source, Table 1, Table 2, the softmax ablation, Table 3."""
    parts = [f"# {metrics.get('title', 'MatSpray evaluation')}"]
    notes = list(metrics.get("notes", ()))
    if metrics.get("lpips"):
        notes.append(f"LPIPS: {metrics['lpips']}")
    if notes:
        parts.append("\n".join(f"- {note}" for note in notes))
    sections = (
        ("Table 1: relighting and material maps", "table1", material_table, "No relighting or material evaluation."),
        ("Table 2: ablation (Full / Supervised / Proj. Average)", "table2", ablation_table, "No ablation runs."),
        (f"Table 2, {UNION_LABEL}", "table2" + UNION, ablation_table, None),
        ("Ablation: Neural Merger softmax", "softmax", softmax_table, "No softmax ablation runs."),
        (f"Ablation: Neural Merger softmax, {UNION_LABEL}", "softmax" + UNION, softmax_table, None),
        ("Table 3: seconds per stage", "timings", timings_table, "No timings recorded."),
    )
    if metrics.get("objects"):
        sections += (("Per object: variants, their order, seconds", "objects", objects_table, ""),)
    for title, key, render, absent in sections:
        data = metrics.get(key)
        if absent is None and not data:  # an optional section (the union tables of older metrics.json files)
            continue
        parts.append(f"## {title}\n\n" + (render(data) if data else f"_{absent}_"))
    return "\n\n".join(parts) + "\n"


def write_tables(path, metrics: Mapping) -> Path:
    """Write `tables_markdown(metrics)` to `path` atomically (temp file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    tmp.write_text(tables_markdown(metrics), encoding="utf-8")
    os.replace(tmp, path)
    return path


# ------------------------------------------------------------------------------------------ averages over objects
# the paper reports every table as the mean over its benchmark objects
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
