"""`RUN/report.html`: what a person looks at. Pictures of the result next to the ground truth, the
estimated light next to the true one, loss curves and the paper's tables. Images are PNGs in
`RUN/report/`, referenced relatively, so the folder can be copied or zipped as it is."""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import torch

from matspray.data import View, load_run_scene, read_image, write_image
from matspray.data.images import srgb_to_linear
from matspray.eval.light import light_figures, training_light
from matspray.eval.run_eval import predict_test_views, read_view_truth, unpremultiply
from matspray.eval.tables import tables_markdown
from matspray.method.asset import ENVMAP_FILE, envmap_preview, read_asset, read_history
from matspray.method.masks import ObjectMasks, read_object_masks
from matspray.method.relight import render_gbuffer
from matspray.predictors import read_materials2d, read_predictor_info
from matspray.presets import LABELS, asset_stage
from matspray.render.shade.deferred import shade_gbuffer
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir, write_text_atomic

MAX_VIEWS = 3
STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.6em; } h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; } \
td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: center; }
figure { display: inline-block; margin: 4px; text-align: center; } figcaption { font-size: 0.8em; color: #555; }
img { image-rendering: pixelated; width: 160px; \
background: repeating-conic-gradient(#ddd 0% 25%, #fff 0% 50%) 50% / 16px 16px; }
img.env { width: 320px; } .warn { background: #fff3cd; padding: 0.6em; border: 1px solid #e0c060; }
"""


def markdown_to_html(text: str) -> str:
    """The subset of markdown `tables.md` uses: headings, bullet lists, pipe tables, emphasis."""
    out, rows = [], []

    def flush_table():
        if rows:
            head, body = rows[0], [r for r in rows[2:]]
            out.append(
                "<table><tr>"
                + "".join(f"<th>{inline(c)}</th>" for c in head)
                + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in body)
                + "</table>"
            )
            rows.clear()

    def inline(cell: str) -> str:
        cell = html.escape(cell.strip())
        while cell.count("**") >= 2:
            cell = cell.replace("**", "<b>", 1).replace("**", "</b>", 1)
        if cell.startswith("_") and cell.endswith("_") and len(cell) > 1:
            cell = f"<i>{cell[1:-1]}</i>"
        return cell

    for line in text.splitlines():
        if line.startswith("|"):
            rows.append(line.strip().strip("|").split("|"))
            continue
        flush_table()
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            out.append(f"<h{level + 1}>{inline(line.lstrip('#'))}</h{level + 1}>")
        elif line.startswith("- "):
            out.append(f"<p>• {inline(line[2:])}</p>")
        elif line.strip():
            out.append(f"<p>{inline(line)}</p>")
    flush_table()
    return "\n".join(out)


def loss_curves_svg(histories: dict[str, list[dict]], width: int = 520, height: int = 220) -> str:
    """Inline SVG with one polyline per (variant, loss term), log-scaled losses over steps."""
    colors = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"]
    series = []
    for variant, history in histories.items():
        for term in ("material", "photo"):
            points = [(r["step"], r[term]) for r in history if r.get(term, 0) > 0]
            if points:
                series.append((f"{variant}: {term}", points))
    if not series:
        return "<p><i>No loss curves (no trained variant).</i></p>"
    max_step = max(p[0] for _, pts in series for p in pts)
    logs = [math.log10(p[1]) for _, pts in series for p in pts]
    lo, hi = min(logs), max(logs) + 1e-9
    parts = [
        f'<svg width="{width}" height="{height + 20 * len(series)}" xmlns="http://www.w3.org/2000/svg">',
        f'<rect x="40" y="5" width="{width - 50}" height="{height - 30}" fill="none" stroke="#999"/>',
        f'<text x="0" y="15" font-size="10">{10**hi:.3g}</text><text x="0" y="{height - 25}" '
        f'font-size="10">{10**lo:.3g}</text>',
        f'<text x="{width - 60}" y="{height - 10}" font-size="10">step {max_step}</text>',
    ]
    for i, (label, points) in enumerate(series):
        color = colors[i % len(colors)]
        coords = " ".join(
            f"{40 + (width - 50) * s / max_step:.1f},{5 + (height - 30) * (hi - math.log10(v)) / (hi - lo):.1f}"
            for s, v in points
        )
        parts.append(f'<polyline fill="none" stroke="{color}" stroke-width="1.2" points="{coords}"/>')
        parts.append(
            f'<text x="45" y="{height + 12 + 20 * i}" font-size="12" fill="{color}">{html.escape(label)}</text>'
        )
    parts.append("</svg>")
    return "\n".join(parts)


class Figures:
    """Writes PNGs into RUN/report/ and remembers the figure markup."""

    def __init__(self, folder: Path):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def image(
        self, name: str, rgb: torch.Tensor, caption: str, alpha: torch.Tensor | None = None, css: str = ""
    ) -> str:
        write_image(
            self.folder / f"{name}.png", rgb.detach().float().cpu().clamp_min(0), None if alpha is None else alpha.cpu()
        )
        return (
            f'<figure><img class="{css}" src="report/{name}.png" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )

    def scalar(self, name: str, values: torch.Tensor, caption: str, alpha: torch.Tensor | None = None) -> str:
        # scalar maps are shown as they are stored (linear values): undo the sRGB encoding of write_image
        return self.image(name, srgb_to_linear(values.clamp(0, 1))[..., None].expand(-1, -1, 3), caption, alpha)


def write_report(run_dir, metrics: dict, data=None) -> Path:
    """Write RUN/report.html (and RUN/report/*.png) from a run and its evaluation `metrics`."""
    run = RunDir(run_dir).require()
    run_dir = run.root
    data = Path(data) if data is not None else Path(run.dataset()["source"])
    scene = load_run_scene(run, data)
    figures = Figures(run_dir / "report")
    sections = [f"<h1>MatSpray result: {html.escape(data.name)}</h1>"]
    info = read_predictor_info(run_dir) if (run_dir / "materials2d" / "predictor.json").exists() else {}
    if info.get("simulated"):
        sections.append(
            '<p class="warn">The 2D material maps of this run are <b>SIMULATED</b> from the ground truth '
            "(a benchmark of the method, not a real diffusion model's output).</p>"
        )
    sections.append(
        "<p>Each row shows one test view. <i>Ground truth</i> is Mitsuba 3's path-traced render of the "
        "true object; <i>ours</i> is the reconstructed asset shaded by split-sum image-based lighting. "
        "Lights marked relit were never seen during training.</p>"
    )
    assets = {v: read_asset(run_dir / asset_stage(v)) for v in run.asset_variants()}
    views: list[View] = scene.test[:MAX_VIEWS]
    env_names = metrics.get("relight_envs", [])
    lights = {
        name: EnvironmentMap.from_file(data / "envmaps" / f"{name}.exr", height=64).prefilter() for name in env_names
    }
    test_predictions, _ = predict_test_views(run_dir, views)  # the baseline of Table 1, None when it cannot run here
    for view in views:
        truth = read_view_truth(view)
        sections.append(f"<h2>Test view {html.escape(view.name)}</h2>")
        sections += [relit_row(view, truth, env, assets, lights[env], figures) for env in env_names]
        if "full" in assets:
            sections.append(materials_row(view, truth, assets["full"], test_predictions, figures))
    if (run_dir / "masks" / "masks.pt").exists():
        sections.append(
            object_masks_section(
                read_object_masks(run_dir / "masks"), scene.train[:MAX_VIEWS], figures, metrics.get("masks")
            )
        )
    if (run_dir / "materials2d").is_dir():  # the 2D predictions the method started from (the training views)
        sections.append(predictions_section(run_dir, scene.train[:MAX_VIEWS], figures))
    sections.append(light_section(run_dir, data, env_names, figures))
    histories = {v: read_history(run_dir / asset_stage(v)) for v in assets}
    sections.append("<h2>Loss curves (refinement)</h2>" + loss_curves_svg({k: v for k, v in histories.items() if v}))
    sections.append(markdown_to_html(tables_markdown(metrics)))
    sections.append(
        "<details><summary>metrics.json</summary><pre>"
        f"{html.escape(json.dumps(metrics.get('table1', {}), indent=1))}</pre></details>"
    )
    path = run_dir / "report.html"
    write_text_atomic(path, html_page(sections))
    return path


def html_page(sections: list[str]) -> str:
    """The report's HTML page around its sections."""
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>MatSpray report</title>"
        f"<style>{STYLE}</style></head><body>{''.join(sections)}</body></html>"
    )


def relit_row(view: View, truth, env: str, assets: dict, light, figures: "Figures") -> str:
    """One test view under light `env`: the ground truth, then every variant's asset."""
    cells = [figures.image(f"{view.name}_{env}_gt", truth.relit[env], f"ground truth, {env}", truth.mask)]
    for variant, asset in assets.items():
        gbuffer = render_gbuffer(asset, view.camera, light)
        rgb = unpremultiply(shade_gbuffer(gbuffer, view.camera, light), gbuffer.alpha)
        cells.append(figures.image(f"{view.name}_{env}_{variant}", rgb, f"{LABELS[variant]}, {env}", gbuffer.alpha))
    return "<div>" + "".join(cells) + "</div>"


def materials_row(view: View, truth, asset, test_predictions: dict | None, figures: "Figures") -> str:
    """One test view's material maps and normals: the full asset's, the truth's and (where it can run here) the 2D
    prediction's, side by side."""
    gbuffer = render_gbuffer(asset, view.camera)
    normals = torch.nn.functional.normalize(gbuffer.normals, dim=-1) * 0.5 + 0.5
    gt_normal_path = view.path.with_name(f"{view.name}_normal.exr")
    cells = [
        figures.image(f"{view.name}_basecolor_ours", gbuffer.base_color, "base color, ours", gbuffer.alpha),
        figures.image(f"{view.name}_basecolor_gt", truth.basecolor, "base color, truth", truth.mask),
        figures.scalar(f"{view.name}_roughness_ours", gbuffer.roughness, "roughness, ours", gbuffer.alpha),
        figures.scalar(f"{view.name}_roughness_gt", truth.roughness, "roughness, truth", truth.mask),
        figures.scalar(f"{view.name}_metallic_ours", gbuffer.metallic, "metallic, ours", gbuffer.alpha),
        figures.scalar(f"{view.name}_metallic_gt", truth.metallic, "metallic, truth", truth.mask),
        figures.image(f"{view.name}_normal_ours", _srgb_inverse(normals), "normals, ours", gbuffer.alpha),
    ]
    if test_predictions is not None:
        m = test_predictions[view.name]
        name = f"pred2d_test_{view.name}"
        cells[2:2] = [figures.image(f"{name}_basecolor", m.basecolor, "base color, 2D prediction", truth.mask)]
        cells[5:5] = [figures.scalar(f"{name}_roughness", m.roughness, "roughness, 2D prediction", truth.mask)]
        cells[8:8] = [figures.scalar(f"{name}_metallic", m.metallic, "metallic, 2D prediction", truth.mask)]
    if gt_normal_path.exists():
        gt_normals, _ = read_image(gt_normal_path)
        picture = _srgb_inverse(gt_normals * 0.5 + 0.5)
        cells.append(figures.image(f"{view.name}_normal_gt", picture, "normals, truth", truth.mask))
    return "<div>" + "".join(cells) + "</div>"


def predictions_section(run_dir: Path, views: list[View], figures: "Figures") -> str:
    """The 2D maps of the training views the method started from."""
    train_maps = read_materials2d(run_dir, views)
    cells = []
    for view in views:
        m = train_maps[view.name]
        cells.append(
            figures.image(f"pred2d_{view.name}_basecolor", m.basecolor, f"2D base color, {view.name}", view.alpha)
        )
        cells.append(
            figures.scalar(f"pred2d_{view.name}_roughness", m.roughness, f"2D roughness, {view.name}", view.alpha)
        )
        cells.append(
            figures.scalar(f"pred2d_{view.name}_metallic", m.metallic, f"2D metallic, {view.name}", view.alpha)
        )
    return "<h2>2D material predictions (input of the method, training views)</h2><div>" + "".join(cells) + "</div>"


def light_section(run_dir: Path, data: Path, env_names: list, figures: "Figures") -> str:
    """The estimated light beside the dataset's lights, with the estimate's figures against the training light;
    empty when there is no light to show."""
    cells = []
    estimated = run_dir / asset_stage("full") / ENVMAP_FILE
    light_note = ""
    if estimated.exists():
        estimate = EnvironmentMap.from_file(estimated).map.detach()
        cells.append(figures.image("envmap_estimated", envmap_preview(estimate), "estimated light (full)", css="env"))
        truth = training_light(data)
        if truth is not None:
            figures_of_light = light_figures(estimate, truth[1])
            light_note = (
                f" Estimate against the training light '{html.escape(truth[0])}': total variation of log radiance "
                f"{figures_of_light['tv_ratio']:.2f} x the truth's, "
                f"irradiance correlation {figures_of_light['irradiance_correlation']:.3f}."
            )
    for path in sorted((data / "envmaps").glob("*.exr")) if (data / "envmaps").is_dir() else []:
        role = "held-out light" if path.stem in env_names else "training light"
        preview = envmap_preview(EnvironmentMap.from_file(path, height=64).map)
        cells.append(figures.image(f"envmap_{path.stem}", preview, f"{role}: {path.stem}", css="env"))
    if not cells:
        return ""
    return (
        "<h2>Environment light</h2><p>Tone-mapped lat-long maps (up is the top row). The estimated light "
        "is only determined up to what the training views reveal."
        + light_note
        + "</p><div>"
        + "".join(cells)
        + "</div>"
    )


def object_masks_section(masks: ObjectMasks, views: list[View], figures: Figures, agreement: dict | None) -> str:
    """A capture without masks: the object region and the masks made from it, over the training photos."""
    cells = []
    for view in views:
        mask = masks.masks["train"][view.name]
        cells.append(
            figures.image(
                f"mask_{view.name}", view.image * (0.25 + 0.75 * mask[..., None]), f"object mask, {view.name}"
            )
        )
    iou = (
        ""
        if agreement is None
        else (
            f" Against the true masks of the test views: IoU {agreement['iou_mean']:.3f} on average, "
            f"{agreement['iou_min']:.3f} at worst."
        )
    )
    return (
        f"<h2>Object masks (the capture has none)</h2><p>The object is the {int(masks.inside.sum())} "
        "Gaussians inside the "
        f"{html.escape(masks.region.describe())}; their rendered alpha is each view's mask (dimmed outside).{iou}</p>"
        "<div>" + "".join(cells) + "</div>"
    )


def _srgb_inverse(values: torch.Tensor) -> torch.Tensor:
    """Values meant to be shown as stored (normals as colours): pre-decode so write_image stores them."""
    return srgb_to_linear(values.clamp(0, 1))
