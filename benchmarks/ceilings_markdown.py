"""The rows of `benchmarks.ceilings` and their markdown: the tables per error model, what each of `full`'s materials
costs it, and where the relighting from the lifted truth to the true G-buffer goes."""

from __future__ import annotations

from benchmarks.generalise_tables import fmt
from matspray.material import GROUPS

CHANNEL_GROUPS = dict(zip(("base", "rough", "metal"), GROUPS.values()))  # row names of `matspray.material.GROUPS`
# rows shading the lifted truth's G-buffer at each test view with parts of it taken from the truth: (materials,
# normals, alpha) each from the asset's G-buffer ("asset") or the truth ("true"; `benchmarks.ceiling_gbuffers`).
# Between the lifted truth (all "asset") and the true G-buffer (all "true"), each splits off the factor it swaps
GBUFFER_ROWS = {
    "lifted truth, true alpha": ("asset", "asset", "true"),
    "lifted truth, true normals": ("asset", "true", "asset"),
    "true maps, Gaussian normals": ("true", "asset", "true"),
}
ROWS = (
    "proj-average",
    "full",
    "full, true light",
    "full, true light, PA brightness",
    *(f"full, true {c}" for c in CHANNEL_GROUPS),
    "full, truth's brightness",
    "softmax oracle",
    *(f"oracle {c} only" for c in CHANNEL_GROUPS),
    "true base, PA brightness",
    "lifted truth, PA brightness",
    "lifted truth",
    "lifted truth, full's normals",
    *GBUFFER_ROWS,
    "true G-buffer",
)
FIGURES = ("relight", "basecolor", "roughness", "metallic")


def mean_rows(per_object: list[dict]) -> dict:
    """{row: {figure: mean over objects}} of the rows every object has (a results file of an older version lacks the
    newer rows), a figure averaged only where every object has it, finite."""
    means = {}
    for row in (r for r in ROWS if all(r in o for o in per_object)):
        values = {f: [o[row].get(f) for o in per_object] for f in FIGURES}
        means[row] = {
            f: sum(v) / len(v) for f, v in values.items() if all(x is not None and abs(x) != float("inf") for x in v)
        }
    return means


def markdown(set_name: str, preset: str, results: dict) -> list[str]:
    lines = [
        f"## Ceilings: {set_name} set, preset {preset}",
        "",
        "Relighting PSNR (dB) on the test views under the held-out lights; material PSNR of each row's materials. "
        "Per object: the relighting PSNR of the main rows.",
        "",
    ]
    for model, per_object in results.items():
        means = mean_rows([o["rows"] for o in per_object])
        lines += [
            f"### error model `{model}` (SIMULATED predictor), mean of {len(per_object)} objects",
            "",
            "| row | relight | vs proj-average | base | rough | metal |",
            "|---|---|---|---|---|---|",
        ]
        base = means.get("proj-average", {}).get("relight")  # None where `--rows` left proj-average out
        for row, m in means.items():
            gap = None if "relight" not in m or base is None else m["relight"] - base
            lines.append(
                f"| {row} | {fmt(m.get('relight'))} | {'' if row == 'proj-average' else fmt(gap)} | "
                + " | ".join(fmt(m.get(c)) for c in FIGURES[1:])
                + " |"
            )
        columns = [  # of the main rows, those this pass computed (`--rows`)
            row
            for row in (
                "proj-average",
                "full",
                "full, true light",
                "softmax oracle",
                "lifted truth, PA brightness",
                "lifted truth",
                "true G-buffer",
            )
            if row in means
        ]
        lines += ["", "| object | " + " | ".join(columns) + " |", "|" + "---|" * (1 + len(columns))]
        lines += [
            f"| {o['object']} | " + " | ".join(fmt(o["rows"][k]["relight"]) for k in columns) + " |" for o in per_object
        ]
        lines.append("")
        for row in (
            "full",
            "full, true light",
            "full, true light, PA brightness",
            "softmax oracle",
            "lifted truth, PA brightness",
            "lifted truth",
        ):
            if row not in means or "proj-average" not in means:
                continue
            gains = [o["rows"][row]["relight"] - o["rows"]["proj-average"]["relight"] for o in per_object]
            lines.append(f"- {row} - proj-average >= 1 dB on {sum(g >= 1.0 for g in gains)}/{len(gains)} objects")
        lines.append("")
        lines += material_costs(means)
        lines += decomposition(means)
    return lines


def material_costs(means: dict) -> list[str]:
    """Markdown of what each of `full`'s materials costs its relighting (the lifted truth's in its place), from
    `mean_rows`; none where a row is missing (a results file of an older version)."""
    rows = {f"full, true {c}": c for c in CHANNEL_GROUPS} | {"full, truth's brightness": "base brightness and tint"}
    if not all("relight" in means.get(row, {}) for row in ("full", *rows)):
        return []
    full = means["full"]["relight"]
    costs = ", ".join(f"{name} {fmt(means[row]['relight'] - full)}" for row, name in rows.items())
    return [f"- `full` with the lifted truth's materials in place of its own gains (dB): {costs}", ""]


# the rows from the lifted truth to the true G-buffer, and the factors each has wrong (the lifted truth's) or fixed
DECOMPOSITION = {
    "lifted truth": "wrong: normals, alpha, material blur",
    "lifted truth, full's normals": "normals `full`'s (refined) instead of the geometry's",
    "lifted truth, true alpha": "fixed: alpha (the silhouette)",
    "lifted truth, true normals": "fixed: normals",
    "true maps, Gaussian normals": "fixed: material blur, alpha",
    "true G-buffer": "fixed: all (the shading model's error is left)",
}


def decomposition(means: dict) -> list[str]:
    """Markdown of where the relighting PSNR between the lifted truth and the true G-buffer goes, from `mean_rows`;
    none where a row of it is missing (a results file of an older version)."""
    if not all("relight" in means.get(row, {}) for row in DECOMPOSITION):
        return []
    relight = {row: means[row]["relight"] for row in DECOMPOSITION}
    start, end = relight["lifted truth"], relight["true G-buffer"]
    lines = [
        f"Where the {fmt(end - start)} dB from the lifted truth to the true G-buffer go: what fixing factors gains "
        "over the lifted truth, and what the factors left wrong still cost against the true G-buffer.",
        "",
        "| row | relight | gain over lifted truth | left to true G-buffer | factors |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {row} | {fmt(r)} | {fmt(r - start)} | {fmt(end - r)} | {DECOMPOSITION[row]} |" for row, r in relight.items()
    ]
    normals = end - relight["true maps, Gaussian normals"]  # the normals alone wrong
    materials = end - relight["lifted truth, true normals"]  # the material blur (+ alpha) alone wrong
    lines += [
        "",
        f"- the Gaussians' normals alone cost {fmt(normals)} dB, the lift's material blur (+ alpha) alone "
        f"{fmt(materials)} dB (each with the other fixed): {fmt(normals + materials)} dB against the gap's "
        f"{fmt(end - start)}; the difference ({fmt(end - start - normals - materials)} dB) is their interaction "
        "(negative: each costs less while the other is wrong too)",
        "",
    ]
    return lines
