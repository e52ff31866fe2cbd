"""The real development objects' tables: the README's table of baked shadows (`--set shadows=on`) against the
default unshadowed shading (the same objects, error model and variants, one `benchmarks.generalise` pass with each
shading, the second reusing the first's predictions, geometry and lift), relighting PSNR per object and the mean;
and docs/dev/softmax.md's table of the two forms of the ablation without the softmax, from a third pass."""

from __future__ import annotations

import json
from pathlib import Path

SHADOWS_REAL_DEV = ("generalise-real-dev-shadows-off.json", "generalise-real-dev-shadows-on.json")
SHADOW_VARIANTS = ("full", "proj-average", "no-softmax")


def relight_by_object(report: dict, model: str) -> dict[str, dict[str, float]]:
    """{object name: {variant: relighting PSNR}} of one error model of a generalise results file."""
    return {o["object"]["name"]: o["figures"]["relight"] for o in report["models"][model]["objects"]}


def shadow_rows(off: dict, on: dict, model: str) -> list[str]:
    """Rows `| object | full off / on | ... | full - no-softmax off / on |`, then the mean over the common objects."""
    first, second = relight_by_object(off, model), relight_by_object(on, model)
    names = [name for name in first if name in second]
    if not names:
        raise SystemExit(f"benchmarks.tables: shadows: the two passes share no object under `{model}`")

    def cells(pick) -> list[str]:
        pairs = [(pick(first[n]), pick(second[n])) for n in names]
        return [f"{a:.2f} / {b:.2f}" for a, b in pairs], pairs

    rows, means = [], []
    for pick in [lambda r, v=v: r[v] for v in SHADOW_VARIANTS] + [lambda r: r["full"] - r["no-softmax"]]:
        texts, pairs = cells(pick)
        rows.append(texts)
        means.append(f"{sum(a for a, _ in pairs) / len(pairs):.2f} / {sum(b for _, b in pairs) / len(pairs):.2f}")
    lines = [f"| {name} | " + " | ".join(column[i] for column in rows) + " |" for i, name in enumerate(names)]
    return lines + [f"| **mean of {len(names)}** | " + " | ".join(means) + " |"]


def table_shadows(results: Path, names: tuple[str, str] = SHADOWS_REAL_DEV) -> str:
    """Relighting PSNR (dB) without / with baked shadows, per object and variant, with `full` minus `no-softmax`."""
    off, on = (json.loads((results / name).read_text()) for name in names)
    models = [m for m in off["models"] if m in on["models"]]
    head = " | ".join(f"{v} off / on" for v in SHADOW_VARIANTS)
    lines = []
    for model in models:
        lines += [
            f"Error model `{model}` (SIMULATED predictor), relighting PSNR (dB) under two held-out lights:",
            "",
            f"| object | {head} | full - no-softmax off / on |",
            "| --- |" + " ---: |" * (len(SHADOW_VARIANTS) + 1),
            *shadow_rows(off, on, model),
            "",
        ]
    return "\n".join(lines).rstrip()


def table_shadows_mean(results: Path, names: tuple[str, str] = SHADOWS_REAL_DEV) -> str:
    """The README's two rows: each shading's mean relighting PSNR (dB) per variant over the objects of both passes."""
    off, on = (json.loads((results / name).read_text()) for name in names)
    lines = []
    for model in [m for m in off["models"] if m in on["models"]]:
        first, second = relight_by_object(off, model), relight_by_object(on, model)
        names_both = [name for name in first if name in second]
        lines += [
            f"| shading ({len(names_both)} object{'s' * (len(names_both) != 1)}, `{model}`) | "
            + " | ".join(SHADOW_VARIANTS)
            + " |",
            "| --- |" + " ---: |" * len(SHADOW_VARIANTS),
        ]
        for label, figures in (("unshadowed (the default)", first), ("baked shadows (`--set shadows=on`)", second)):
            means = [sum(figures[n][v] for n in names_both) / len(names_both) for v in SHADOW_VARIANTS]
            lines.append(f"| {label} | " + " | ".join(f"{m:.2f}" for m in means) + " |")
    return "\n".join(lines)


NO_SOFTMAX_RAW = "generalise-real-dev-no-softmax-raw.json"  # --variants no-softmax --setting ...unconstrained=raw


def table_no_softmax_forms(results: Path, names: tuple[str, str] = (SHADOWS_REAL_DEV[0], NO_SOFTMAX_RAW)) -> str:
    """Relighting PSNR (dB) of `full` and of `no-softmax` with our weights (offsets from the projection average) and
    with the raw weights (the released code's merger without its softmax), per object and the mean."""
    ours, raw = (json.loads((results / name).read_text()) for name in names)
    lines = []
    for model in [m for m in ours["models"] if m in raw["models"]]:
        first, second = relight_by_object(ours, model), relight_by_object(raw, model)
        both = [name for name in first if name in second]
        rows = [(n, first[n]["full"], first[n]["no-softmax"], second[n]["no-softmax"]) for n in both]
        rows.append((f"**mean of {len(both)}**", *(sum(r[i] for r in rows) / len(rows) for i in (1, 2, 3))))
        lines += [
            f"| object (`{model}`) | full | no-softmax, offset weights | no-softmax, raw weights |",
            "| --- | ---: | ---: | ---: |",
            *(f"| {n} | {a:.2f} | {b:.2f} | {c:.2f} |" for n, a, b, c in rows),
        ]
    return "\n".join(lines)


SHADOW_TABLES = {
    "no-softmax-forms": (table_no_softmax_forms, [SHADOWS_REAL_DEV[0], NO_SOFTMAX_RAW]),
    "shadows-real-dev": (table_shadows, list(SHADOWS_REAL_DEV)),
    "shadows-real-dev-mean": (table_shadows_mean, list(SHADOWS_REAL_DEV)),
}
