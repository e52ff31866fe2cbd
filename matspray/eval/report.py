"""`RUN/report.html`: what a person looks at, the answer first. At the top, the asset relit under each held-out light
beside the truth, the headline figures and whether each ablation agrees with the paper (`matspray.eval.page.summary`);
then every test view's pictures, the 2D predictions, the estimated light beside the true ones, the loss curves, the
paper's tables and a glossary. Every picture enlarges on a click. Images are PNGs in `RUN/report/`, referenced
relatively, and no path of the machine is written on the page, so the folder can be copied or zipped as it is."""

from __future__ import annotations

import html
import json
from pathlib import Path

import torch

from matspray.data import View, load_run_scene, read_image
from matspray.eval.light import light_figures, training_light
from matspray.eval.page.glossary import glossary_html
from matspray.eval.page.markup import Figures, html_page, markdown_to_html, srgb_inverse
from matspray.eval.page.paths import lpips_line, object_name, page_places
from matspray.eval.page.plot import loss_curves_svg
from matspray.eval.page.summary import summary_section
from matspray.eval.run_eval import (
    EVAL_ENV_HEIGHT,
    load_relight_lights,
    predict_test_views,
    read_view_truth,
    unpremultiply,
)
from matspray.eval.tables import tables_markdown
from matspray.method.asset import ENVMAP_FILE, envmap_preview, read_asset, read_history
from matspray.method.masks import ObjectMasks, read_object_masks
from matspray.method.relight import render_gbuffer
from matspray.predictors import read_materials2d, read_predictor_info
from matspray.presets import LABELS, asset_stage
from matspray.render.shade.deferred import shade_gbuffer
from matspray.render.shade.envmap import EnvironmentMap, sample_latlong
from matspray.render.shade.latlong import pixel_directions
from matspray.rundir import RunDir, write_text_atomic

MAX_VIEWS = 3


def write_report(run_dir, metrics: dict, data=None) -> Path:
    """Write RUN/report.html (and RUN/report/*.png) from a run and its evaluation `metrics`."""
    run = RunDir(run_dir).require()
    run_dir = run.root
    data = Path(data) if data is not None else Path(run.dataset()["source"])
    scene = load_run_scene(run, data)
    figures = Figures(run_dir / "report")
    name = object_name(data)
    info = read_predictor_info(run_dir) if (run_dir / "materials2d" / "predictor.json").exists() else {}
    views: list[View] = scene.test[:MAX_VIEWS]
    view_sections = test_view_sections(run, data, views, metrics.get("relight_envs", []), figures)
    sections = [f"<h1>MatSpray result: {html.escape(name)}</h1>"]
    if info.get("simulated"):
        sections.append(
            '<p class="warn">The 2D material maps of this run are <b>SIMULATED</b> from the ground truth '
            "(a benchmark of the method, not a real diffusion model's output).</p>"
        )
    sections.append(summary_section(metrics, views[0].name if views else None, figures, bool(info.get("simulated"))))
    sections += view_sections
    sections += detail_sections(run, data, scene, metrics, figures)
    sections.append(markdown_to_html(tables_markdown(page_metrics(metrics, name))))
    sections.append(
        "<details><summary>metrics.json (Table 1)</summary><pre>"
        f"{html.escape(json.dumps(metrics.get('table1', {}), indent=1))}</pre></details>"
    )
    sections.append(glossary_html("".join(sections)))
    path = run_dir / "report.html"
    write_text_atomic(path, html_page(sections, f"MatSpray: {name}", page_places(run_dir, data)))
    return path


def page_metrics(metrics: dict, name: str) -> dict:
    """`metrics` as the page's tables show them: titled by the object, the LPIPS line without the machine's paths."""
    return {**metrics, "title": f"The paper's tables: {name}", "lpips": lpips_line(metrics.get("lpips"))}


def test_view_sections(run: RunDir, data: Path, views: list[View], env_names: list, figures: Figures) -> list[str]:
    """Each test view: the truth and every variant under each held-out light, then the material maps."""
    assets = {v: read_asset(run.path(asset_stage(v))) for v in run.asset_variants()}
    lights = load_relight_lights(data, env_names)
    test_predictions, _ = predict_test_views(run.root, views)  # the baseline of Table 1, None when it cannot run here
    sections = [
        "<h2>Test views</h2><p>Each row shows one test view under one light. <i>Ground truth</i> is Mitsuba 3's "
        "path-traced render of the true object; the others are the reconstructed assets (the method and its "
        "ablations) shaded by split-sum image-based lighting. The lights are held out: never seen in training.</p>"
    ]
    for view in views:
        truth = read_view_truth(view)
        sections.append(f"<h3>Test view {html.escape(view.name)}</h3>")
        sections += [relit_row(view, truth, env, assets, lights[env], figures) for env in env_names]
        if "full" in assets:
            sections.append(materials_row(view, truth, assets["full"], test_predictions, figures))
    return sections


def detail_sections(run: RunDir, data: Path, scene, metrics: dict, figures: Figures) -> list[str]:
    """What follows the test views: the object masks (a capture without them), the 2D predictions of the training
    views, the lights and the loss curves."""
    sections = []
    if run.path("masks", "masks.pt").exists():
        sections.append(
            object_masks_section(
                read_object_masks(run.path("masks")), scene.train[:MAX_VIEWS], figures, metrics.get("masks")
            )
        )
    if run.path("materials2d").is_dir():  # the 2D predictions the method started from (the training views)
        sections.append(predictions_section(run.root, scene.train[:MAX_VIEWS], figures))
    sections.append(light_section(run.root, data, metrics.get("relight_envs", []), figures))
    histories = {v: read_history(run.path(asset_stage(v))) for v in run.asset_variants()}
    sections.append("<h2>Loss curves (refinement)</h2>" + loss_curves_svg({k: v for k, v in histories.items() if v}))
    return sections


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
        figures.image(f"{view.name}_normal_ours", srgb_inverse(normals), "normals, ours", gbuffer.alpha),
    ]
    if test_predictions is not None:
        m = test_predictions[view.name]
        name = f"pred2d_test_{view.name}"
        cells[2:2] = [figures.image(f"{name}_basecolor", m.basecolor, "base color, 2D prediction", truth.mask)]
        cells[5:5] = [figures.scalar(f"{name}_roughness", m.roughness, "roughness, 2D prediction", truth.mask)]
        cells[8:8] = [figures.scalar(f"{name}_metallic", m.metallic, "metallic, 2D prediction", truth.mask)]
    if gt_normal_path.exists():
        gt_normals, _ = read_image(gt_normal_path)
        picture = srgb_inverse(gt_normals * 0.5 + 0.5)
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
    """The estimated light beside the dataset's true lights, all shown at the held-out lights' evaluation size (the
    estimate as the shader reads it: bilinear between its few pixels), with the estimate's figures against the
    training light; empty when there is no light to show."""
    cells, note = [], ""
    estimated = run_dir / asset_stage("full") / ENVMAP_FILE
    if estimated.exists():
        estimate = EnvironmentMap.from_file(estimated).map.detach()
        height, width = estimate.shape[:2]
        caption = (
            f"estimated light (Full): {width} x {height} px, shown bilinear at "
            f"{2 * EVAL_ENV_HEIGHT} x {EVAL_ENV_HEIGHT}, as the shader reads it"
        )
        cells.append(figures.image("envmap_estimated", envmap_preview(as_shaded(estimate)), caption, css="env"))
        truth = training_light(data)
        if truth is not None:
            measured = light_figures(estimate, truth[1])
            note = (
                f" Estimate against the training light '{html.escape(truth[0])}': total variation of log radiance "
                f"{measured['tv_ratio']:.2f} x the truth's, irradiance correlation "
                f"{measured['irradiance_correlation']:.3f}."
            )
    training = training_light(data)
    paths = sorted((data / "envmaps").glob("*.exr")) if (data / "envmaps").is_dir() else []
    paths.sort(key=lambda path: training is None or path.stem != training[0])  # the training light first
    for path in paths:
        role = "held-out light" if path.stem in env_names else "training light"
        light = EnvironmentMap.from_file(path, height=EVAL_ENV_HEIGHT).map  # as evaluation relights with it
        caption = f"{role}: {path.stem}, {light.shape[1]} x {light.shape[0]} px"
        preview = envmap_preview(light)
        cells.append(figures.image(f"envmap_{path.stem}", preview, caption, css="env"))
    if not cells:
        return ""
    return (
        "<h2>Environment light</h2><p>Tone-mapped lat-long maps (up is the top row), each scaled to its own "
        "brightest 1 %. The estimated light is only determined up to what the training views reveal."
        + note
        + "</p><div>"
        + "".join(cells)
        + "</div>"
    )


def as_shaded(map: torch.Tensor, height: int = EVAL_ENV_HEIGHT) -> torch.Tensor:  # [h, 2h, 3] -> [height, 2 height, 3]
    """A lat-long light at `height` rows as the shader samples it (bilinear, wrapping in azimuth): how a small
    estimated light is shown beside the larger true ones, without the blocks of its pixels."""
    return sample_latlong(map, pixel_directions(height, 2 * height, dtype=map.dtype))


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
