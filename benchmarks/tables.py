"""The generated tables of README.md and docs/**/*.md, from the result files committed under docs/results/.

    python -m benchmarks.tables            # rewrite every generated table in place
    python -m benchmarks.tables --check    # change nothing; exit 1 naming each differing table or hand-typed figure

A generated table sits between two markers in a markdown file:

    <!-- table: NAME -->
    ...                  (written by this script; do not edit by hand)
    <!-- /table -->

NAME is one of TABLES below; each is made from files in docs/results/ (which the benchmarks write:
`benchmarks.generalise` and `benchmarks.real_captures` copy their results there when run with their
default --out), except `cli`, which is docs/cli.md's reference made from the argparse parsers of
`matspray`. The per-model tables reuse benchmarks.generalise's own formatting (`model_table`).
"""

from __future__ import annotations

import argparse
import re
import sys
from functools import partial
from pathlib import Path

from benchmarks.tables_cli import table_cli
from benchmarks.tables_extra import EXTRA
from benchmarks.tables_figures import hand_typed_figures
from benchmarks.tables_files import grouped, object_table, read
from benchmarks.tables_real_eval import REAL_EVAL_TABLES
from benchmarks.tables_shadows import SHADOW_TABLES
from matspray.predictors import CHANNELS
from matspray.presets import PAPER_ABLATION, PAPER_SOFTMAX

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path("docs") / "results"  # relative to the repository root
MARKER = re.compile(r"(<!-- table: ([\w.-]+) -->\n)(.*?)(<!-- /table -->)", re.S)
MODELS = ("paper", "harsh", "outliers")


def fmt(value, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def short(name: str) -> str:
    """dev-b-00-seed2000 -> dev-b-00"""
    return re.sub(r"-seed\d+$", "", name)


# ------------------------------------------------------------------------------------------ generalisation
EVAL_NOPRIOR = "generalise-dev-b-noprior.json"
EVAL_NORMALS = "generalise-dev-b-normals.json"  # the same three models with predicted normals on (the default since)
DEV_NOPRIOR = "generalise-dev-noprior-s38.json"


def noprior_row(lead: list[str], label: str, relight: dict, full: dict, no_prior: dict) -> str:
    """One row of `noprior_rows`: relighting PSNR by variant, and the 3D materials' PSNR per channel (channel ->
    dB) of the full method and of no-prior."""
    cells = lead + [label, fmt(relight.get("full")), fmt(relight.get("no-prior"))]
    cells += [f"{fmt(full[c])} / {fmt(no_prior[c])}" for c in CHANNELS]
    return "| " + " | ".join(cells) + " |"


def noprior_rows(report: dict, models) -> list[str]:
    """Rows `| [model |] object | relight full | relight no-prior | base | rough | metal |` (full / no-prior)."""
    rows = []
    for model in models:
        result = report["models"][model]
        lead = [model] if len(models) > 1 else []
        for o in result["objects"]:
            f = o["figures"]
            rows.append(
                noprior_row(lead, short(o["object"]["name"]), f["relight"], f["materials_3d"], f["materials_no_prior"])
            )
        s = result["summary"]
        full, no_prior = ({c: s[key][c]["psnr"] for c in CHANNELS} for key in ("materials_3d", "materials_no_prior"))
        rows.append(noprior_row(lead, f"mean of {len(result['objects'])}", s["relight"], full, no_prior))
    return rows


def noprior_head(with_model: bool) -> list[str]:
    head = ["model"] if with_model else []
    head += [
        "object",
        "relight full",
        "relight no-prior",
        "base full / no-prior",
        "rough full / no-prior",
        "metal full / no-prior",
    ]
    align = (["---"] if with_model else []) + ["---"] + ["---:"] * 5
    return ["| " + " | ".join(head) + " |", "| " + " | ".join(align) + " |"]


def wins_lines(report: dict, models) -> list[str]:
    lines = []
    for model in models:
        wins = {k: w for k, w in report["models"][model]["summary"]["wins"].items() if w["of"]}
        lines.append(f"- `{model}`: " + ", ".join(f"{k} {w['wins']}/{w['of']}" for k, w in wins.items()))
    return lines


def table_noprior_dev(results: Path) -> str:
    report = read(results, DEV_NOPRIOR)
    return "\n".join(noprior_head(False) + noprior_rows(report, ["paper"]))


def table_noprior_eval(results: Path) -> str:
    report = read(results, EVAL_NOPRIOR)
    models = [m for m in MODELS if m in report["models"]]
    return "\n".join(
        noprior_head(True) + noprior_rows(report, models) + ["", "Wins (out of 6):"] + wins_lines(report, models)
    )


def table_generalise_eval(results: Path) -> str:
    """The protocol's full per-model tables (benchmarks.generalise's format), relighting and materials of
    `full` and `no-prior` and the 2D predictions, per object, with the seconds."""
    report = read(results, EVAL_NOPRIOR)
    lines = []
    for model in [m for m in MODELS if m in report["models"]]:
        count = len(report["models"][model]["objects"])
        lines += [f"Error model `{model}` (SIMULATED predictor), {count} objects:", ""] + object_table(report, model)
    return "\n".join(lines).rstrip()


def table_headline(results: Path, name: str = EVAL_NORMALS) -> str:
    """docs/benchmarks.md: means over dev-b per error model, full method against no-prior and the 2D maps."""
    report = read(results, name)
    lines = [
        "| error model | relight full | relight no-prior | base colour full / no-prior / 2D | roughness full / "
        "no-prior / 2D | metallic full / no-prior / 2D | full > no-prior |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for model in [m for m in MODELS if m in report["models"]]:
        s = report["models"][model]["summary"]
        win = s["wins"]["full > no-prior"]
        cells = [f"`{model}`", fmt(s["relight"]["full"]), fmt(s["relight"]["no-prior"])]
        cells += [
            " / ".join(fmt(s[g][c]["psnr"]) for g in ("materials_3d", "materials_no_prior", "materials_2d"))
            for c in CHANNELS
        ]
        lines.append("| " + " | ".join(cells + [f"{win['wins']} of {win['of']}"]) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ the `dr` error model
EVAL_DR = "generalise-dev-b-dr.json"
EVAL_DR_256 = "generalise-dev-b-256px-dr.json"  # the same protocol with the objects at 256 px
DEV_DR = "generalise-dev-dr.json"
EVAL_THREE_256 = "generalise-dev-b-256px-three.json"  # paper, harsh, outliers at 256 px: full and proj-average
EVAL_PA_128 = "generalise-dev-b-proj-average.json"  # the same three at 128 px: proj-average beside EVAL_NOPRIOR's full


def table_models_eval(results: Path, name: str = EVAL_THREE_256) -> str:
    """Each error model's per-object table (benchmarks.generalise's format), one after the other."""
    report = read(results, name)
    models = [model for model in MODELS if model in report["models"]]
    return "\n\n".join(f"`{model}`:\n\n" + "\n".join(object_table(report, model)).strip() for model in models)


def table_dr_eval(results: Path, name: str = EVAL_DR) -> str:
    """Every variant per object under `dr` (benchmarks.generalise's format)."""
    return "\n".join(object_table(read(results, name), "dr")).rstrip()


def table_dr_orderings(results: Path, name: str = EVAL_DR) -> str:
    """The paper's orderings: full minus each other variant in relighting, the paper's and ours."""
    from benchmarks.generalise_tables import wins

    result = read(results, name)["models"]["dr"]
    mean, objects = result["summary"]["relight"], result["objects"]
    lines = [
        "| full against | paper: full, it (dB) | paper: full - it | ours: full, it (dB) | ours: full - it "
        "| full wins |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for other, paper in (
        ("proj-average", PAPER_ABLATION),
        ("supervised", PAPER_ABLATION),
        ("no-softmax", PAPER_SOFTMAX),
        ("no-prior", None),
    ):
        theirs = ["—", "—"] if paper is None else [f"{paper['full']:.2f}, {paper[other]:.2f}"]
        theirs += [] if paper is None else [f"{paper['full'] - paper[other]:+.2f}"]
        ours = [f"{mean['full']:.2f}, {mean[other]:.2f}", f"{mean['full'] - mean[other]:+.2f}"]
        won = wins([o["figures"]["relight"] for o in objects], [("", lambda r: r["full"], lambda r: r[other])])[""]
        wins_cell = f"{won['wins']} of {won['of']}"
        lines.append("| " + " | ".join([f"`{other}`", *theirs, *ours, wins_cell]) + " |")
    return "\n".join(lines)


def object_figures(results: Path, names: list[str], model: str) -> dict:
    """{object: figures} of `model` from one or more results files of the same objects (say, full and proj-average
    run apart): their relighting PSNRs merged, the materials from the first file that has them."""
    merged: dict = {}
    for name in names:
        for o in read(results, name)["models"][model]["objects"]:
            figures = merged.setdefault(o["object"]["name"], {"relight": {}})
            figures["relight"].update({k: v for k, v in o["figures"]["relight"].items() if v is not None})
            for key in ("materials_3d", "materials_2d"):
                if o["figures"].get(key) and all(v is not None for v in o["figures"][key].values()):
                    figures.setdefault(key, o["figures"][key])
    return merged


def table_resolutions(results: Path, models=("dr",), low=(EVAL_DR,), high=(EVAL_DR_256,)) -> str:
    """The evaluation set at 128 px (`low` results files) and at 256 px (`high`), object by object (those done at
    both): what the resolution changes in full's gain over proj-average and in its 3D materials against the 2D maps."""
    lead = ["error model"] if len(models) > 1 else []
    lines = [
        "| "
        + " | ".join(lead + ["object", "full - proj-average, 128 / 256 px"])
        + " | "
        + " | ".join(f"3D - 2D {c}, 128 / 256 px" for c in CHANNELS)
        + " |",
        "| " + " | ".join(["---"] * len(lead) + ["---"] + ["---:"] * 4) + " |",
    ]

    def row(label: list, figures: list) -> str:
        cells = [" / ".join(f"{f['relight']['full'] - f['relight']['proj-average']:+.2f}" for f in figures)]
        for c in CHANNELS:
            cells.append(" / ".join(f"{f['materials_3d'][c] - f['materials_2d'][c]:+.2f}" for f in figures))
        return "| " + " | ".join(label + cells) + " |"

    for model in models:
        runs = [object_figures(results, list(names), model) for names in (low, high)]
        names = [name for name in runs[1] if name in runs[0]]
        tag = [f"`{model}`"] if lead else []
        for name in names:
            lines.append(row(tag + [short(name)], [runs[0][name], runs[1][name]]))
        means = [
            {
                key: {k: sum(run[n][key][k] for n in names) / len(names) for k in run[names[0]][key]}
                for key in ("relight", "materials_3d", "materials_2d")
            }
            for run in runs
        ]
        lines.append(row(tag + [f"**mean of {len(names)}**"], means))
    return "\n".join(lines)


def table_dr_dev(results: Path) -> str:
    """The development set under `dr`: full against proj-average per object."""
    result = read(results, DEV_DR)["models"]["dr"]
    lines = ["| object | relight full | relight proj-average | full - proj-average |", "| --- | ---: | ---: | ---: |"]
    for o in result["objects"]:
        r = o["figures"]["relight"]
        lines.append(
            f"| {short(o['object']['name'])} | {fmt(r['full'])} | {fmt(r['proj-average'])} | "
            f"{r['full'] - r['proj-average']:+.2f} |"
        )
    m = result["summary"]["relight"]
    lines.append(
        f"| mean of {len(result['objects'])} | {fmt(m['full'])} | {fmt(m['proj-average'])} | "
        f"{m['full'] - m['proj-average']:+.2f} |"
    )
    return "\n".join(lines)


CEILINGS_DR = "ceilings-dev-dr.json"


def table_dr_ceilings(results: Path) -> str:
    """benchmarks.ceilings' tables for `dr` on the development set (its own formatting)."""
    from benchmarks.ceilings_markdown import markdown

    lines = markdown("dev", "demo", {"dr": read(results, CEILINGS_DR)["dr"]})
    start = next(i for i, line in enumerate(lines) if line.startswith("| row |"))
    return "\n".join(lines[start:]).rstrip()


# what was tried on the development set under `dr`: (label, result file, variant)
DR_TRIED = (
    ("default: proj-average", DEV_DR, "proj-average"),
    ("default: full", DEV_DR, "full"),
    ("full, L_Image weight 0.25 (`--refine material_weight=0.25`)", "generalise-dev-dr-material0.25.json", "full"),
    (
        "full, 1 800 refinement steps instead of 600 (`--refine iterations=1800`)",
        "generalise-dev-dr-steps1800.json",
        "full",
    ),
    ("`--method paper`: proj-average", "generalise-dev-paper-dr-paper-method.json", "proj-average"),
    ("`--method paper`: full", "generalise-dev-paper-dr-paper-method.json", "full"),
)


def table_dr_tried(results: Path) -> str:
    """Relighting of each configuration tried on the development set under `dr`, per object and mean."""
    runs = [(label, read(results, name)["models"]["dr"], variant) for label, name, variant in DR_TRIED]
    names = [short(o["object"]["name"]) for o in runs[0][1]["objects"]]
    base = runs[0][1]["summary"]["relight"]["proj-average"]
    lines = [
        "| configuration | " + " | ".join(names) + " | mean | vs proj-average |",
        "| --- |" + " ---: |" * (len(names) + 2),
    ]
    for label, result, variant in runs:
        per_object = [fmt(o["figures"]["relight"][variant]) for o in result["objects"]]
        mean = result["summary"]["relight"][variant]
        lines.append(f"| {label} | " + " | ".join(per_object) + f" | {fmt(mean)} | {mean - base:+.2f} |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ real captures
CAPTURES = ("skull", "stitch")


def captures(results: Path) -> dict:
    return {name: read(results, f"real-captures-{name}.json") for name in CAPTURES}


def metric_triple(entry: dict) -> str:
    return f"{entry['psnr']:.2f} / {entry['ssim']:.3f} / {entry['lpips']:.3f}"


def table_real_captures(results: Path) -> str:
    c = captures(results)

    def row(label, get):
        return f"| {label} | " + " | ".join(get(c[name]) for name in CAPTURES) + " |"

    def sfm(r, key, text):
        return text(r["sfm"]) if r.get("sfm") else ("(poses given)" if key == "registered" else "")

    def coverage(r):
        shares = [share for _, share in r["mask_coverage"]]
        return f"{100 * min(shares):.1f} % to {100 * max(shares):.1f} %"

    def stages(r):
        s = r["stage_seconds"]
        refine = next(v for k, v in s.items() if k.startswith("asset"))
        return " / ".join(f"{v:.0f}" for v in (s["geometry"], s["masks"], s["lift"], refine))

    def box(r):
        lo, hi = r["glb_box"]
        return "(" + ", ".join(f"{v:.3f}" for v in lo) + ") .. (" + ", ".join(f"{v:.3f}" for v in hi) + ")"

    return "\n".join(
        [
            "| | " + " | ".join(CAPTURES) + " |",
            "| --- | " + " | ".join("---:" for _ in CAPTURES) + " |",
            row(
                "photos registered by `matspray colmap`",
                lambda r: sfm(r, "registered", lambda s: f"{s['registered']} of {s['photos']}"),
            ),
            row("mean reprojection error", lambda r: sfm(r, "error", lambda s: f"{s['reprojection_px']:.3f} px")),
            row("held-out views", lambda r: str(len(r["mask_coverage"]))),
            row("held-out PSNR / SSIM / LPIPS, geometry", lambda r: metric_triple(r["heldout"]["radiance"])),
            row(
                "held-out PSNR / SSIM / LPIPS, asset under its light", lambda r: metric_triple(r["heldout"]["no-prior"])
            ),
            row(
                "training-view PSNR, geometry / asset",
                lambda r: f"{r['train']['radiance']['psnr']:.2f} / {r['train']['no-prior']['psnr']:.2f}",
            ),
            row("mask coverage of the held-out views", coverage),
            row(
                "Gaussians: geometry / asset (object region)",
                lambda r: f"{grouped(r['gaussians_geometry'])} / {grouped(r['gaussians_asset'])}",
            ),
            row("object region (automatic)", lambda r: r["region"].replace(" (chosen automatically)", "")),
            row("exported glb box (dataset world)", box),
            row("geometry / masks / lift / refine seconds", stages),
        ]
    )


def table_captures_headline(results: Path) -> str:
    """README: held-out photos of the two real captures, inside the object mask."""
    c = captures(results)
    lines = [
        "| capture | photos | held-out views | PSNR / SSIM / LPIPS, asset under its estimated light | "
        "Gaussians in the asset |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for name in CAPTURES:
        r = c[name]
        photos = f"cut to the object ({r['crop_gain']:.2f}x across)" if r.get("crop_gain") else "whole"
        lines.append(
            f"| {name} | {photos} | {len(r['mask_coverage'])} | {metric_triple(r['heldout']['no-prior'])} | "
            + f"{grouped(r['gaussians_asset'])} |"
        )
    return "\n".join(lines)


QUALITY_SKULL = "real-captures-skull-quality.json"


def table_capture_quality(results: Path) -> str:
    """README, beside its first picture: the skull at the quality preset, held-out photos inside the object mask."""
    r = read(results, QUALITY_SKULL)
    asset = next(key for key in r["heldout"] if key != "radiance")  # the user's asset the run made
    seconds = sum(r["stage_seconds"].values())
    peak = next(step["peak_mib"] for step in r["steps"] if step["command"].startswith("matspray run "))
    flash = " and flash" if r.get("camera_light") else ""  # a flash at the camera, learned on flash photos

    def cells(entry: dict) -> str:
        return f"{metric_triple(entry)} | {entry['gradient_share']:.2f}"

    return "\n".join(
        [
            "| render, held-out photos inside the mask | PSNR / SSIM / LPIPS | detail (gradient energy share) |",
            "| --- | ---: | ---: |",
            f"| Gaussian Splatting's own colours | {cells(r['heldout']['radiance'])} |",
            f"| the {asset} asset under its estimated light{flash} | {cells(r['heldout'][asset])} |",
            "",
            f"Preset `{r['preset']}`: {len(r['mask_coverage'])} held-out photos, "
            + grouped(r["gaussians_asset"])
            + f" Gaussians in the asset; `matspray run` took {seconds / 60:.0f} min and at most"
            + f" {peak / 1024:.1f} GB of memory on a 2-core CPU.",
        ]
    )


DEMO_BACKENDS = "demo-backends.json"


def table_demo_backends(results: Path) -> str:
    """The demo's figures with backend torch and numba (benchmarks.demo_backends), and where measured each figure's
    change from the refinement's seed alone."""
    from benchmarks.demo_backends import comparison_lines, largest_seed_spread

    result = read(results, DEMO_BACKENDS)
    within = sum(abs(r["difference"]) <= result["tolerance"] for r in result["rows"])
    summary = f"largest difference {result['largest']:.2f} dB; {within} of {len(result['rows'])} within "
    summary += f"{result['tolerance']} dB"
    if "seed_runs" in result:
        summary += f"; the refinement seed alone moves a figure by up to {largest_seed_spread(result):.2f} dB"
    return "\n".join([*comparison_lines(result), "", summary])


# name -> (function of the results folder, the result files it reads)
TABLES = {
    "dev-b-headline": (table_headline, [EVAL_NORMALS]),
    "normals-eval": (partial(table_models_eval, name=EVAL_NORMALS), [EVAL_NORMALS]),
    "captures-headline": (table_captures_headline, [f"real-captures-{n}.json" for n in CAPTURES]),
    "capture-quality": (table_capture_quality, [QUALITY_SKULL]),
    "no-prior-dev": (table_noprior_dev, [DEV_NOPRIOR]),
    "no-prior-eval": (table_noprior_eval, [EVAL_NOPRIOR]),
    "generalise-eval": (table_generalise_eval, [EVAL_NOPRIOR]),
    "real-captures": (table_real_captures, [f"real-captures-{n}.json" for n in CAPTURES]),
    "dr-eval": (table_dr_eval, [EVAL_DR]),
    "dr-orderings": (table_dr_orderings, [EVAL_DR]),
    "dr-eval-256": (partial(table_dr_eval, name=EVAL_DR_256), [EVAL_DR_256]),
    "dr-orderings-256": (partial(table_dr_orderings, name=EVAL_DR_256), [EVAL_DR_256]),
    "dr-resolutions": (table_resolutions, [EVAL_DR, EVAL_DR_256]),
    "three-eval-256": (table_models_eval, [EVAL_THREE_256]),
    "three-resolutions": (
        partial(table_resolutions, models=MODELS, low=(EVAL_NOPRIOR, EVAL_PA_128), high=(EVAL_THREE_256,)),
        [EVAL_NOPRIOR, EVAL_PA_128, EVAL_THREE_256],
    ),
    "dr-dev": (table_dr_dev, [DEV_DR]),
    "dr-ceilings": (table_dr_ceilings, [CEILINGS_DR]),
    "dr-tried": (table_dr_tried, [name for _, name, _ in DR_TRIED]),
    "demo-backends": (table_demo_backends, [DEMO_BACKENDS]),
    "cli": (table_cli, []),
    **EXTRA,
    **SHADOW_TABLES,
    **REAL_EVAL_TABLES,
}


def documents(root: Path) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]  # docs/, docs/guide/, docs/dev/


def render(text: str, results: Path, cache: dict, where: str) -> str:
    def replace(match):
        name = match.group(2)
        if name not in TABLES:
            raise SystemExit(f"benchmarks.tables: {where}: unknown table '{name}' (known: {', '.join(TABLES)})")
        if name not in cache:
            cache[name] = TABLES[name][0](results)
        return match.group(1) + cache[name] + "\n" + match.group(4)

    return MARKER.sub(replace, text)


def differing(root: Path = ROOT, results: Path | None = None, write: bool = False) -> list[str]:
    """'FILE: table NAME' for each generated table whose text differs from what docs/results gives
    (rewritten in place when `write`)."""
    results = results or root / RESULTS
    cache, found = {}, []
    for path in documents(root):
        text = path.read_text()
        new = render(text, results, cache, path.name)
        if new == text:
            continue
        old = {m.group(2): m.group(3) for m in MARKER.finditer(text)}
        fresh = {m.group(2): m.group(3) for m in MARKER.finditer(new)}
        found += [f"{path.relative_to(root)}: table {name}" for name in fresh if old.get(name) != fresh[name]]
        if write:
            path.write_text(new)
    return found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.tables", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--check", action="store_true", help="change nothing; exit 1 naming each differing table or hand-typed figure"
    )
    parser.add_argument("--root", type=Path, default=ROOT, help="repository root (default: this checkout)")
    args = parser.parse_args(argv)
    found = differing(args.root, write=not args.check)
    if args.check:
        for item in found:
            print(f"differs from docs/results: {item}")
        if found:
            print("run `python -m benchmarks.tables` to regenerate them")
        typed = hand_typed_figures(args.root)  # a figure these pages quote must come from a table of this script
        for item in typed:
            print(f"a figure typed by hand outside a generated table: {item} (generate it, or move it to docs/dev)")
        return 1 if found or typed else 0
    print("\n".join(f"rewritten: {item}" for item in found) or "every generated table is up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
