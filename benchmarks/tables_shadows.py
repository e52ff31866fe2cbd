"""The real development objects' tables: the README's table of baked shadows (`--set shadows=on`) against the
default unshadowed shading (the same objects, error model and variants, one `benchmarks.generalise` pass with each
shading, the second reusing the first's predictions, geometry and lift), relighting PSNR per object and the mean;
docs/dev/softmax.md's table of the two forms of the ablation without the softmax, from a third pass, its table of
the ablation under three error models (the default pass, one under `harsh`, one under `outliers`) and under two
training lights (the default pass and one with every object trained under a low sun)."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

from benchmarks.tables_files import mean

SHADOWS_REAL_DEV = ("generalise-real-dev-shadows-off.json", "generalise-real-dev-shadows-on.json")
SHADOW_VARIANTS = ("full", "proj-average", "no-softmax")


def relight_by_object(report: dict, model: str) -> dict[str, dict[str, float]]:
    """{object name: {variant: relighting PSNR}} of one error model of a generalise results file."""
    return {o["object"]["name"]: o["figures"]["relight"] for o in report["models"][model]["objects"]}


def paired_passes(results: Path, names: tuple[str, str]):
    """For each error model both results files hold: (model, first's figures, second's figures, the objects both
    hold, in the first's order); two passes without a common object are refused."""
    first_report, second_report = (json.loads((results / name).read_text()) for name in names)
    for model in [m for m in first_report["models"] if m in second_report["models"]]:
        first, second = relight_by_object(first_report, model), relight_by_object(second_report, model)
        common = [name for name in first if name in second]
        if not common:
            raise SystemExit(f"benchmarks.tables: {names[0]} and {names[1]} share no object under `{model}`")
        yield model, first, second, common


def shadow_rows(first: dict, second: dict, common: list[str]) -> list[str]:
    """Rows `| object | full off / on | ... | full - no-softmax off / on |`, then the mean over the objects."""
    picks = [lambda r, v=v: r[v] for v in SHADOW_VARIANTS] + [lambda r: r["full"] - r["no-softmax"]]

    def row(label: str, objects: list[str]) -> str:
        cells = [f"{mean(p(first[n]) for n in objects):.2f} / {mean(p(second[n]) for n in objects):.2f}" for p in picks]
        return f"| {label} | " + " | ".join(cells) + " |"

    return [row(name, [name]) for name in common] + [row(f"**mean of {len(common)}**", common)]


def table_shadows(results: Path, names: tuple[str, str] = SHADOWS_REAL_DEV) -> str:
    """Relighting PSNR (dB) without / with baked shadows, per object and variant, with `full` minus `no-softmax`."""
    head = " | ".join(f"{v} off / on" for v in SHADOW_VARIANTS)
    lines = []
    for model, first, second, common in paired_passes(results, names):
        lines += [
            f"Error model `{model}` (SIMULATED predictor), relighting PSNR (dB) under two held-out lights:",
            "",
            f"| object | {head} | full - no-softmax off / on |",
            "| --- |" + " ---: |" * (len(SHADOW_VARIANTS) + 1),
            *shadow_rows(first, second, common),
            "",
        ]
    return "\n".join(lines).rstrip()


def table_shadows_mean(results: Path, names: tuple[str, str] = SHADOWS_REAL_DEV) -> str:
    """The README's two rows: each shading's mean relighting PSNR (dB) per variant over the objects of both passes."""
    lines = []
    for model, first, second, common in paired_passes(results, names):
        count = f"{len(common)} object{'s' * (len(common) != 1)}"
        lines += [
            f"| shading ({count}, `{model}`) | " + " | ".join(SHADOW_VARIANTS) + " |",
            "| --- |" + " ---: |" * len(SHADOW_VARIANTS),
        ]
        for label, figures in (("unshadowed (the default)", first), ("baked shadows (`--set shadows=on`)", second)):
            cells = [f"{mean(figures[n][v] for n in common):.2f}" for v in SHADOW_VARIANTS]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


NO_SOFTMAX_RAW = "generalise-real-dev-no-softmax-raw.json"  # --variants no-softmax --setting ...unconstrained=raw


def table_no_softmax_forms(results: Path, names: tuple[str, str] = (SHADOWS_REAL_DEV[0], NO_SOFTMAX_RAW)) -> str:
    """Relighting PSNR (dB) of `full` and of `no-softmax` with our weights (offsets from the projection average) and
    with the raw weights (the released code's merger without its softmax), per object and the mean."""
    lines = []
    for model, ours, raw, common in paired_passes(results, names):
        rows = [(n, ours[n]["full"], ours[n]["no-softmax"], raw[n]["no-softmax"]) for n in common]
        rows.append((f"**mean of {len(common)}**", *(mean(r[i] for r in rows) for i in (1, 2, 3))))
        lines += [
            f"| object (`{model}`) | full | no-softmax, offset weights | no-softmax, raw weights |",
            "| --- | ---: | ---: | ---: |",
            *(f"| {n} | {a:.2f} | {b:.2f} | {c:.2f} |" for n, a, b, c in rows),
        ]
    return "\n".join(lines)


SOFTMAX_OUTLIERS = "generalise-real-dev-outliers.json"  # --models outliers --variants full proj-average no-softmax
SOFTMAX_HARSH = "generalise-real-dev-harsh.json"  # --models harsh --variants full proj-average no-softmax
SOFTMAX_SUNSET = "generalise-real-dev-train-sunset.json"  # --train-light sunset --variants full proj-average no-softmax
SOFTMAX_BY_MODEL = (SHADOWS_REAL_DEV[0], SOFTMAX_HARSH, SOFTMAX_OUTLIERS)  # the default pass, then the two models
SOFTMAX_BY_LIGHT = (SHADOWS_REAL_DEV[0], SOFTMAX_SUNSET)  # the default pass (drawn lights), then a low sun


def table_softmax_by_model(results: Path, names: tuple[str, ...] = SOFTMAX_BY_MODEL) -> str:
    """Relighting PSNR (dB) of `full`, `proj-average` and `no-softmax` per object under each error model of the
    files (default shading), with `full`'s margins over the two, and the mean over the objects; a pass that trained
    every object under one light (`--train-light`) says which."""
    lines = [
        "| error model | object | full | proj-average | no-softmax | full - proj-average | full - no-softmax |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name in names:
        report = json.loads((results / name).read_text())
        light = report["settings"].get("train_light")
        for model in report["models"]:
            figures = relight_by_object(report, model)
            rows = [(n, f["full"], f["proj-average"], f["no-softmax"]) for n, f in figures.items()]
            rows.append((f"**mean of {len(rows)}**", *(mean(r[i] for r in rows) for i in (1, 2, 3))))
            label = f"`{model}`" + (f", trained under {light}" if light else "")
            for n, a, b, c in rows:
                lines.append(f"| {label} | {n} | {a:.2f} | {b:.2f} | {c:.2f} | {a - b:+.2f} | {a - c:+.2f} |")
    return "\n".join(lines)


SHADOW_TABLES = {
    "softmax-real-dev-models": (table_softmax_by_model, list(SOFTMAX_BY_MODEL)),
    "softmax-real-dev-sunset": (partial(table_softmax_by_model, names=SOFTMAX_BY_LIGHT), list(SOFTMAX_BY_LIGHT)),
    "no-softmax-forms": (table_no_softmax_forms, [SHADOWS_REAL_DEV[0], NO_SOFTMAX_RAW]),
    "shadows-real-dev": (table_shadows, list(SHADOWS_REAL_DEV)),
    "shadows-real-dev-mean": (table_shadows_mean, list(SHADOWS_REAL_DEV)),
}
