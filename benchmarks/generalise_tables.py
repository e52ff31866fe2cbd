"""The generalisation protocol's figures and markdown (`benchmarks.generalise`): the figures of one (object,
model) run, the means over objects and wins out of N, the per-model tables, the results page and the
development-set table of choices. `benchmarks.tables` reuses `model_table` for the docs.
"""

from __future__ import annotations

import math
from pathlib import Path

from matspray.batch.demo import DEMO_SIZES
from matspray.errors import ConfigError
from matspray.eval.tables import average_tables
from matspray.predictors import CHANNELS
from matspray.predictors.error_models import ERROR_MODELS
from matspray.presets import BASELINE, LABELS, MAPLESS
from matspray.presets import VARIANT_NAMES as VARIANTS
from matspray.rundir import read_json

SHORT = {"basecolor": "base", "roughness": "rough", "metallic": "metal"}


def object_figures(metrics: dict) -> dict:
    """The protocol's figures of one (object, model) run from its eval/metrics.json content."""
    variants = metrics.get("variants", {})
    relight = {v: variants[v]["summary"]["relighting"]["psnr"] for v in VARIANTS if v in variants}
    full = variants.get("full", {}).get("summary", {})
    baseline = variants.get(BASELINE, {}).get("summary", {})
    predictions = metrics.get("predictions_2d", {})
    return {
        "relight": relight,
        "materials_3d": {c: full[c]["psnr"] for c in CHANNELS if c in full},
        "materials_no_prior": {c: baseline[c]["psnr"] for c in CHANNELS if c in baseline},
        "materials_2d": {c: predictions[c]["psnr"] for c in CHANNELS if c in predictions},
        # after a per-channel scale fitted to the truth (TensoIR / IRGS), where the evaluation made them
        "relight_aligned": {v: aligned_psnr(variants[v], "relighting_aligned") for v in VARIANTS if v in variants},
        "basecolor_aligned": {v: aligned_psnr(variants[v], "basecolor_aligned") for v in VARIANTS if v in variants},
        "normal_error": {
            v: variants[v]["summary"]["normals"]["error_deg"]
            for v in VARIANTS
            if "normals" in variants.get(v, {}).get("summary", {})
        },
    }


def aligned_psnr(variant: dict, row: str) -> float | None:
    """A variant's scale-aligned PSNR of `row`; None where its evaluation had no aligned rows."""
    return variant.get("summary", {}).get(row, {}).get("psnr")


def wins(figures: list[dict], pairs) -> dict:
    """For each (label, a, b): how many objects have a > b (strictly), out of those with both."""
    out = {}
    for label, a, b in pairs:
        both = [(a(f), b(f)) for f in figures if a(f) is not None and b(f) is not None]
        out[label] = {"wins": sum(x > y for x, y in both), "of": len(both)}
    return out


def model_summary(per_object: list[dict]) -> dict:
    """Means over objects (the paper's averaging, via matspray.eval.tables.average_tables) and wins out of N."""
    averaged = average_tables([o["metrics"] for o in per_object])
    table1 = averaged["table1"]
    relight = {
        v: averaged["table2"].get(label, averaged["softmax"].get(label, {})).get("psnr")
        for v, label in (
            ("full", "Full"),
            ("proj-average", "Proj. Average"),
            ("supervised", "Supervised"),
            ("no-softmax", "Without Softmax"),
        )
    }
    for name in MAPLESS:  # the variants without 2D maps: Table 1's columns
        relight[name] = table1.get(LABELS[name], {}).get("relighting", {}).get("psnr")
    figures = [o["figures"] for o in per_object]

    def get(group, key):
        return lambda f: f[group].get(key)

    pairs = [
        ("full > proj-average", get("relight", "full"), get("relight", "proj-average")),
        ("full > no-softmax", get("relight", "full"), get("relight", "no-softmax")),
        ("full > no-prior", get("relight", "full"), get("relight", BASELINE)),
        (
            "full > no-prior basecolor",
            get("materials_3d", "basecolor"),
            lambda f: f.get("materials_no_prior", {}).get("basecolor"),
        ),
    ]
    pairs += [(f"3D > 2D {c}", get("materials_3d", c), get("materials_2d", c)) for c in CHANNELS]
    return {
        "relight": {k: v for k, v in relight.items() if v is not None},
        "relight_aligned": mean_over_objects(figures, "relight_aligned"),
        "basecolor_aligned": mean_over_objects(figures, "basecolor_aligned"),
        "materials_3d": {c: table1.get("Ours", {}).get(c, {}) for c in CHANNELS},
        "materials_no_prior": {c: table1.get(LABELS[BASELINE], {}).get(c, {}) for c in CHANNELS},
        "materials_2d": {c: table1.get("2D predictions", {}).get(c, {}) for c in CHANNELS},
        "wins": wins(figures, pairs),
        "tables": averaged,
    }


def mean_over_objects(figures: list[dict], group: str) -> dict:
    """Variant -> the mean of `group`'s figure over the objects, for the variants every object has it for."""
    values: dict[str, list[float]] = {}
    for f in figures:
        for variant, value in f.get(group, {}).items():
            if value is not None:
                values.setdefault(variant, []).append(value)
    return {v: math.fsum(x) / len(x) for v, x in values.items() if len(x) == len(figures)}


def fmt(value) -> str:
    if value is None:
        return "—"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.2f}"


def metallic_mean(entry: dict) -> str:
    """The paper's rule: '∞*k/mean' when k objects had infinite metallic PSNR."""
    if not entry:
        return "—"
    infinite = int(entry.get("psnr_infinite", 0))
    if infinite == 0 or infinite == entry.get("objects"):
        return fmt(entry.get("psnr"))
    return f"inf*{infinite}/{fmt(entry.get('psnr'))}"


def model_table(model: str, per_object: list[dict], summary: dict, variants) -> list[str]:
    """Markdown lines: one row per object, the mean row, and the wins."""
    label = "SIMULATED predictor" if model in ERROR_MODELS else "ground-truth maps (sanity row)"
    head = ["object", "train light", "relit under"] + [f"relight {v}" for v in variants]
    baseline = BASELINE in variants  # the no-prior variant's materials, beside full's
    head += [f"3D {SHORT[c]}" for c in CHANNELS] + ([f"no-prior {SHORT[c]}" for c in CHANNELS] if baseline else [])
    head += [f"2D {SHORT[c]}" for c in CHANNELS]
    normals = [v for v in variants if any(v in o["figures"].get("normal_error", {}) for o in per_object)]
    head += [f"normals {v} (deg)" for v in normals] + ["s"]  # results of older versions have no normal errors
    lines = [f"### error model `{model}` ({label}; unaligned PSNR)", "", "| " + " | ".join(head) + " |"]
    lines.append("|" + "---|" * len(head))
    for o in per_object:
        f = o["figures"]
        cells = [o["object"]["name"], o["object"]["env"], ", ".join(o["object"]["relight_envs"])]
        cells += [fmt(f["relight"].get(v)) for v in variants]
        cells += [fmt(f["materials_3d"].get(c)) for c in CHANNELS]
        cells += [fmt(f.get("materials_no_prior", {}).get(c)) for c in CHANNELS] if baseline else []
        cells += [fmt(f["materials_2d"].get(c)) for c in CHANNELS]
        cells += [fmt(f.get("normal_error", {}).get(v)) for v in normals]
        lines.append("| " + " | ".join(cells + [f"{o['seconds']:.0f}"]) + " |")
    s3, s2 = summary["materials_3d"], summary["materials_2d"]
    mean = [f"**mean of {len(per_object)}**", "", ""] + [fmt(summary["relight"].get(v)) for v in variants]
    for group in (s3, summary["materials_no_prior"]) if baseline else (s3,):
        mean += [fmt(group[c].get("psnr")) for c in CHANNELS[:2]] + [metallic_mean(group["metallic"])]
    mean += [fmt(s2[c].get("psnr")) for c in CHANNELS[:2]] + [metallic_mean(s2["metallic"])]
    for v in normals:
        errors = [o["figures"]["normal_error"][v] for o in per_object if v in o["figures"].get("normal_error", {})]
        mean.append(fmt(sum(errors) / len(errors)))
    lines.append("| " + " | ".join(mean + [f"{sum(o['seconds'] for o in per_object) / len(per_object):.0f}"]) + " |")
    counted = {k: w for k, w in summary["wins"].items() if w["of"]}  # a pair with a variant not run has no count
    lines += ["", "wins: " + ", ".join(f"{k} {w['wins']}/{w['of']}" for k, w in counted.items()), ""]
    return lines + aligned_table(per_object, summary, variants)


def aligned_table(per_object: list[dict], summary: dict, variants) -> list[str]:
    """The relighting and base-colour PSNR after a per-channel scale fitted to the truth (the TensoIR / IRGS
    convention), per object and their mean; nothing where the evaluation made no aligned rows."""
    shown = [v for v in variants if v in summary.get("relight_aligned", {})]
    if not shown:
        return []
    head = ["object"] + [f"relight {v}" for v in shown] + [f"base {v}" for v in shown]
    lines = [
        "Scale-aligned (each channel times the median ratio to the truth on the object: the TensoIR / IRGS "
        "convention; the table above is unaligned):",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for o in per_object:
        f = o["figures"]
        cells = [o["object"]["name"]] + [fmt(f["relight_aligned"].get(v)) for v in shown]
        lines.append("| " + " | ".join(cells + [fmt(f["basecolor_aligned"].get(v)) for v in shown]) + " |")
    mean = [f"**mean of {len(per_object)}**"] + [fmt(summary["relight_aligned"].get(v)) for v in shown]
    mean += [fmt(summary["basecolor_aligned"].get(v)) for v in shown]
    return lines + ["| " + " | ".join(mean) + " |", ""]


def markdown(settings: dict, results: dict, summaries: dict, timing: list[dict]) -> list[str]:
    size = DEMO_SIZES[settings["preset"]]
    res = settings.get("resolution", size.res)  # older result files do not say
    lines = [
        f"## Generalisation protocol: {settings['set']} set, preset {settings['preset']} ({res} "
        f"px, {size.views} views)",
        "",
        f"method: {settings['method']}; without: {', '.join(settings['without']) or 'nothing'}; settings: "
        f"{settings['settings'] or 'as the method sets them'}; refine overrides: "
        f"{settings['refine_overrides'] or 'none'}; geometry overrides: "
        f"{settings.get('geometry_overrides') or 'none'}; tag {settings['tag']}",
        "PSNR in dB on the test views (object mask); relighting under the two held-out lights; "
        "3D = the full method's materials, "
        "2D = the predictor's maps of the same test views. Simulated predictors are SIMULATED from the ground truth.",
        "",
    ]
    for model, per_object in results.items():
        lines += model_table(model, per_object, summaries[model], settings["variants"])
    lines += [
        "### seconds per object",
        "",
        "| object | synth | geometry (each model's, or once when shared) | "
        + " | ".join(f"{m} (all variants + eval)" for m in results)
        + " | total |",
        "|" + "---|" * (4 + len(results)),
    ]
    for t in timing:
        cells = [t["object"], f"{t['synth']:.0f}", f"{t['geometry']:.0f}"]
        lines.append(
            "| " + " | ".join(cells + [f"{t['models'][m]:.0f}" for m in results] + [f"{t['total']:.0f}"]) + " |"
        )
    mean_total = sum(t["total"] for t in timing) / len(timing)
    lines += [
        "",
        f"mean {mean_total:.0f} s per object ({len(timing)} objects, "
        f"{sum(t['total'] for t in timing) / 3600:.2f} h in all)",
    ]
    return lines


def choices_table(out: Path) -> list[str]:
    """Markdown lines: one row per configuration (results-*.json in `out`) and error model, from the
    saved results: the development-set table of choices."""
    reports = sorted(out.glob("results-*.json"))
    if not reports:
        raise ConfigError(f"{out}: no results-*.json to compare; run the protocol first (with --out {out})")
    lines = [
        "| tag | method | refine overrides | model | objects | relight full | full - proj-average | "
        "full - no-softmax | "
        "full > proj-average | 3D - 2D base | 3D - 2D rough | 3D - 2D metal |",
        "|" + "---|" * 12,
    ]
    for path in reports:
        report = read_json(path)
        settings = report["settings"]
        overrides = ", ".join(f"{k}={v}" for k, v in settings["refine_overrides"].items()) or "none"
        for model, result in report["models"].items():
            summary = result["summary"]
            relight, m3, m2 = summary["relight"], summary["materials_3d"], summary["materials_2d"]

            def gap(a, b):
                return None if a is None or b is None else a - b

            win = summary["wins"]["full > proj-average"]
            lines.append(
                "| "
                + " | ".join(
                    [
                        settings["tag"],
                        str(settings["method"]),
                        overrides,
                        model,
                        str(settings["objects"]),
                        fmt(relight.get("full")),
                        fmt(gap(relight.get("full"), relight.get("proj-average"))),
                        fmt(gap(relight.get("full"), relight.get("no-softmax"))),
                        f"{win['wins']}/{win['of']}",
                        fmt(gap(m3["basecolor"].get("psnr"), m2["basecolor"].get("psnr"))),
                        fmt(gap(m3["roughness"].get("psnr"), m2["roughness"].get("psnr"))),
                        fmt(gap(m3["metallic"].get("psnr"), m2["metallic"].get("psnr"))),
                    ]
                )
                + " |"
            )
    return lines
