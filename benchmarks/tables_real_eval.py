"""The evaluation set's tables: `real-eval` run once on the final defaults with each method (`benchmarks.generalise
--set real-eval --tag final`, and `--method paper --tag final-paper`). The README's headline is the mean relighting
PSNR of each variant per method and error model, as measured and after a per-channel scale fitted to the truth (the
TensoIR / IRGS convention), with `full`'s margins over the other variants and on how many objects it wins; then the
maps of `full`, `no-prior` and the 2D model. docs/benchmarks.md carries the per-object tables
(benchmarks.generalise's own format)."""

from __future__ import annotations

from pathlib import Path

from benchmarks.tables_files import mean, object_table, read
from matspray.predictors import CHANNELS

# one results file per method, in the order the tables show them
REAL_EVAL = ("generalise-real-eval-final.json", "generalise-real-eval-final-paper.json")
OTHERS = ("proj-average", "no-softmax", "no-prior")  # what `full` is compared with, as the paper's tables do
PROTOCOLS = (("relight", "as measured"), ("relight_aligned", "scale-aligned"))


def reports(results: Path, names: tuple[str, ...]) -> list[dict]:
    return [read(results, name) for name in names]


def margin(objects: list[dict], group: str, other: str) -> str:
    """`full` minus `other` on the mean over the objects, and on how many objects `full` is above: '+0.41 (3 of 5)'."""
    pairs = [(o["figures"][group]["full"], o["figures"][group][other]) for o in objects]
    wins = sum(a > b for a, b in pairs)
    return f"{mean(a - b for a, b in pairs):+.2f} ({wins} of {len(pairs)})"


def table_real_eval_headline(results: Path, names: tuple[str, ...] = REAL_EVAL) -> str:
    """Relighting PSNR (dB) on the evaluation objects per method, error model and protocol: each variant's mean and
    `full`'s margins over the others."""
    lines = [
        "| method | error model | protocol | full | "
        + " | ".join(OTHERS)
        + " | "
        + " | ".join(f"full - {o}" for o in OTHERS)
        + " |",
        "| --- | --- | --- |" + " ---: |" * (1 + 2 * len(OTHERS)),
    ]
    for report in reports(results, names):
        method = report["settings"]["method"]
        for model, result in report["models"].items():
            objects = result["objects"]
            for group, protocol in PROTOCOLS:
                cells = [f"{mean(o['figures'][group][v] for o in objects):.2f}" for v in ("full", *OTHERS)]
                cells += [margin(objects, group, other) for other in OTHERS]
                lines.append(f"| `{method}` | `{model}` | {protocol} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_real_eval_maps(results: Path, names: tuple[str, ...] = REAL_EVAL) -> str:
    """The maps' PSNR (dB) on the evaluation objects: `full` / `no-prior` / the 2D model's, per channel (means over
    the objects; metallic by the paper's rule for identical maps), and `full`'s base colour scale-aligned."""
    lines = [
        "| method | error model | base colour full / no-prior / 2D | roughness full / no-prior / 2D | metallic full / "
        "no-prior / 2D | base colour full, scale-aligned |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for report in reports(results, names):
        method = report["settings"]["method"]
        for model, result in report["models"].items():
            summary = result["summary"]
            cells = [
                " / ".join(
                    f"{summary[group][channel]['psnr']:.2f}"
                    for group in ("materials_3d", "materials_no_prior", "materials_2d")
                )
                for channel in CHANNELS
            ]
            cells.append(f"{summary['basecolor_aligned']['full']:.2f}")
            lines.append(f"| `{method}` | `{model}` | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_real_eval_objects(results: Path, names: tuple[str, ...] = REAL_EVAL) -> str:
    """Each method's and error model's per-object table, benchmarks.generalise's own format."""
    parts = []
    for report in reports(results, names):
        for model in report["models"]:
            table = "\n".join(object_table(report, model)).strip()
            parts.append(f"`--method {report['settings']['method']}`, error model `{model}`:\n\n{table}")
    return "\n\n".join(parts)


REAL_EVAL_TABLES = {
    "real-eval-headline": (table_real_eval_headline, list(REAL_EVAL)),
    "real-eval-maps": (table_real_eval_maps, list(REAL_EVAL)),
    "real-eval-objects": (table_real_eval_objects, list(REAL_EVAL)),
}
