"""`RUN/report.html` for a run on a real capture, which has no ground truth to compare with.

What a person checks there instead: held-out photos beside the run's renders of them (views never
trained on), a training photo beside its render, the asset relit under other lights, its material
maps, the light it estimated, and the object region with the masks it gave (the table and the room
must not be part of the asset). The figures are `matspray.eval.heldout`'s."""

from __future__ import annotations

import html
import os
from pathlib import Path

import torch

from matspray.data import load_run_scene
from matspray.eval.heldout import RADIANCE, format_share, heldout_table, photo_renders, read_renderables
from matspray.eval.page.glossary import glossary_html
from matspray.eval.page.markup import Figures, html_page, markdown_to_html, srgb_inverse
from matspray.eval.page.paths import lpips_line, object_name, page_places
from matspray.eval.relit_crops import crop, default_asset, relit_crops, same_capture, square_box
from matspray.eval.report import as_shaded, object_masks_section
from matspray.export.frames import find_glbs, glb_box
from matspray.method.asset import ENVMAP_FILE, envmap_preview
from matspray.method.masks import read_object_masks, read_region
from matspray.method.refine.camera_light import CAMERA_LIGHT_FILE, CameraLight
from matspray.method.relight import background_radiance, render_gbuffer, render_relit
from matspray.presets import LABELS, asset_stage
from matspray.render.backend import rendering_with
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import load_envmap
from matspray.rundir import RunDir, write_text_atomic

MAX_VIEWS = 3
RELIGHT_ENV_HEIGHT = 64
CROP_SIZE = 256  # pixels per column of the side-by-side crops


def _label(key: str) -> str:
    return "geometry (3DGS colours)" if key == RADIANCE else f"{LABELS.get(key, key)}, its estimated light"


def asset_box_note(run: RunDir, assets: dict) -> str:
    """The boxes of the asset and of every mesh exported into the run folder (RUN/*.glb, RUN/export/*.glb), in the
    dataset's world, beside the object region's: what shows that no table or room came along."""
    lines = []
    for variant, asset in assets.items():
        means = asset.gaussians.means.detach().cpu()
        low, high = means.min(0).values.tolist(), means.max(0).values.tolist()
        lines.append(
            f"{LABELS.get(variant, variant)} asset: {len(means)} Gaussians in the box "
            f"({', '.join(f'{v:.3f}' for v in low)}) .. ({', '.join(f'{v:.3f}' for v in high)})"
        )
    for path in find_glbs(run.root):
        low, high = glb_box(path)
        lines.append(
            f"exported mesh {path.relative_to(run.root)}: box ({', '.join(f'{v:.3f}' for v in low)}) "
            f".. ({', '.join(f'{v:.3f}' for v in high)})"
        )
    region = read_region(run.path("masks"))
    if region is not None:
        low, high = region.bounds().tolist()
        lines.append(
            f"object region: {region.describe()}; box ({', '.join(f'{v:.3f}' for v in low)}) "
            f".. ({', '.join(f'{v:.3f}' for v in high)})"
        )
    return "<ul>" + "".join(f"<li>{html.escape(line)}</li>" for line in lines) + "</ul>"


def comparison_section(
    run: RunDir, own: dict, others: list[RunDir], views, light_spec: str, figures: Figures, device
) -> str:
    """Each of `views`: the photo, then `run`'s default asset (from `own`, the assets it has read) and each of
    `others`' relit under `light_spec`, cut to the same square around the object at the same size (`relit_crops`)."""
    name, env = load_envmap(light_spec, height=RELIGHT_ENV_HEIGHT)
    light = EnvironmentMap.from_tensor(env.to(device), learnable=False).prefilter()
    variant = run.default_variant()
    assets = [own[variant]] + [default_asset(r, device) for r in others]
    labels = ["photo", f"{run.root.name} ({variant})"] + [f"{r.root.name} ({r.default_variant()})" for r in others]
    cells = []
    for view in views:
        row = relit_crops(assets, view.camera.to(device), light, view.image, CROP_SIZE)
        if row is not None:
            cells.append(figures.image(f"compare_{view.name}_{name}", row, f"{view.name}, {name}: {', '.join(labels)}"))
    return (
        "<h2>Beside other runs of this capture</h2><p>The object relit under "
        f"{html.escape(name)} over grey, every run cut to the same square around it, at the same size: "
        f"{html.escape(', '.join(os.path.relpath(r.root, run.root) for r in others))} (relative to this run's "
        "folder).</p><div>" + "".join(cells) + "</div>"
    )


def comparable_runs(run: RunDir, compare) -> list[RunDir]:
    """The run folders `compare` as RunDirs; DataError or RunError (before any work) unless each is a run of `run`'s
    capture with an asset."""
    others = [RunDir(path).require() for path in compare]
    if others:
        same_capture([run, *others])
        for other in others:
            other.default_variant()
    return others


def write_capture_report(
    run_dir,
    metrics: dict,
    lights=("studio", "sunset", "forest"),
    credit: str | None = None,
    device="cpu",
    backend: str = "torch",
    compare=(),
) -> Path:
    """Write RUN/report.html (and RUN/report/*.png) for a run without ground truth, from `evaluate_capture`'s metrics.
    `lights`: names or files the asset is relit under; `credit`: a line crediting the photos (shown at the top);
    `compare`: run folders of the same capture (before a change of settings, say) shown beside this one."""
    run = RunDir(run_dir).require()
    others = comparable_runs(run, compare)
    source = run.dataset()["source"]
    scene = load_run_scene(run)
    figures = Figures(run.path("report"))
    name = object_name(source)
    sections = [f"<h1>MatSpray result: {html.escape(name)}</h1>"]
    if credit:
        sections.append(f"<p><i>Photos: {html.escape(credit)}</i></p>")
    sections.append(
        "<p>A real capture: there is no ground truth for materials or light. What can be checked is how well the "
        "run reproduces photos it never trained on (held out), inside the object's mask.</p>"
    )
    sections.append(markdown_to_html(heldout_table(metrics)))

    loaded = read_renderables(run, device)
    held = photo_renders(run, scene.test[:MAX_VIEWS], "test", device, backend, progress=False, renderables=loaded)
    trained = photo_renders(run, scene.train[:1], "train", device, backend, progress=False, renderables=loaded)
    sections.append(sharpness_section(metrics, held[0] if held else None, figures))
    sections += photo_rows("Held-out photos (never trained on) and the run's renders", held, figures)
    sections += photo_rows("A training photo and the run's renders", trained, figures)

    variants, assets = list(loaded.assets), loaded.assets
    views = scene.test[:2] or scene.train[:2]
    with rendering_with(backend), torch.no_grad():
        sections.append(relit_section(assets, views, lights, figures, device))
        if others:
            sections.append(comparison_section(run, assets, others, views, lights[0], figures, device))
        sections += material_rows(assets, views[0].camera.to(device), figures)

    sections.append(estimated_light_section(run, variants, figures))
    sections.append("<h2>Object region</h2>" + asset_box_note(run, assets))
    if run.path("masks", "masks.pt").exists():
        sections.append(
            object_masks_section(read_object_masks(run.path("masks")), scene.train[:MAX_VIEWS], figures, None)
        )
    sections.append(glossary_html("".join(sections)))
    path = run.path("report.html")
    write_text_atomic(path, html_page(sections, f"MatSpray: {name}", page_places(run.root, source)))
    return path


def sharpness_section(metrics: dict, item, figures: Figures) -> str:
    """How sharp the asset is beside the photos it never saw: held-out LPIPS inside the mask (or how to get its
    weights) and each render's gradient energy as a share of the photo's, with the first held-out photo beside the
    renders, cut to the object and enlarged alike."""
    held = metrics["heldout"]["summary"]
    rows = [
        f"| {_label(key)} | {'n/a' if v.get('lpips') is None else format(v['lpips'], '.3f')} | "
        f"{format_share(v.get('gradient_share'))} |"
        for key, v in held.items()
    ]
    header = ["| render | held-out LPIPS ↓ | gradient energy share (photo: 1) |", "| --- | ---: | ---: |"]
    table = "\n".join([*header, *rows])
    missing = any(v.get("lpips") is None for v in held.values())
    how = f"<p>LPIPS: {html.escape(lpips_line(metrics.get('lpips')) or 'n/a')}</p>" if missing else ""
    picture = ""
    box = None if item is None else square_box([item.mask])
    if box is not None:
        columns = [item.view.image, *item.renders.values()]
        strip = torch.cat([crop(c.clamp(0, 1), box, CROP_SIZE) for c in columns], dim=1)
        labels = ", ".join(["photo", *(_label(key) for key in item.renders)])
        caption = f"{item.view.name}, cut to the object: {labels}"
        picture = figures.image(f"sharpness_{item.view.name}", strip, caption, css="strip")
    return (
        "<h2>Sharpness</h2><p>Inside the object mask of the held-out photos: LPIPS (lower: closer to the photo in "
        "what people notice, blur included) and the render's gradient energy as a share of the photo's (the "
        "squared differences of neighbouring pixels: 1 holds as much fine detail as the photo, below 1 is softer)."
        f"</p>{markdown_to_html(table)}{how}<div>{picture}</div>"
    )


def photo_rows(title: str, items, figures: Figures) -> list[str]:
    """A section of photos, each with its object mask and the run's renders of its view."""
    rows = [f"<h2>{title}</h2>"]
    for item in items:
        name = item.view.name
        overlay = item.view.image * (0.25 + 0.75 * item.mask[..., None])
        cells = [
            figures.image(f"photo_{name}", item.view.image, f"photo {name}"),
            figures.image(f"mask_overlay_{name}", overlay, "object mask"),
        ]
        cells += [
            figures.image(f"render_{name}_{key}", rgb, _label(key), item.mask) for key, rgb in item.renders.items()
        ]
        rows.append("<div>" + "".join(cells) + "</div>")
    return rows


def relit_section(assets: dict, views, lights, figures: Figures, device) -> str:
    """Every asset relit under each of `lights` (names or files) in `views`, over the light itself."""
    cells = []
    for spec in lights:
        name, env = load_envmap(spec, height=RELIGHT_ENV_HEIGHT)
        light = EnvironmentMap.from_tensor(env.to(device), learnable=False)
        prefiltered = light.prefilter()
        for variant, asset in assets.items():
            for view in views:
                camera = view.camera.to(device)
                rgb, alpha = render_relit(asset, camera, prefiltered)
                rgb = rgb + background_radiance(light, camera) * (1 - alpha[..., None])
                label = f"{LABELS.get(variant, variant)}, {name}, {view.name}"
                cells.append(figures.image(f"relit_{view.name}_{variant}_{name}", rgb, label))
    return (
        "<h2>Relit under other lights</h2><p>The asset shaded under lights it never saw, over the light itself.</p>"
        "<div>" + "".join(cells) + "</div>"
    )


def material_rows(assets: dict, camera, figures: Figures) -> list[str]:
    """Every asset's base colour, roughness, metallic and normals seen from `camera`."""
    rows = ["<h2>Material maps</h2>"]
    for variant, asset in assets.items():
        gbuffer = render_gbuffer(asset, camera)
        normals = torch.nn.functional.normalize(gbuffer.normals, dim=-1) * 0.5 + 0.5
        label, alpha = LABELS.get(variant, variant), gbuffer.alpha.cpu()
        cells = [
            figures.image(f"maps_{variant}_basecolor", gbuffer.base_color.cpu(), f"base colour, {label}", alpha),
            figures.scalar(f"maps_{variant}_roughness", gbuffer.roughness.cpu(), f"roughness, {label}", alpha),
            figures.scalar(f"maps_{variant}_metallic", gbuffer.metallic.cpu(), f"metallic, {label}", alpha),
            figures.image(f"maps_{variant}_normal", srgb_inverse(normals.cpu()), f"normals, {label}", alpha),
        ]
        rows.append("<div>" + "".join(cells) + "</div>")
    return rows


def estimated_light_section(run: RunDir, variants, figures: Figures) -> str:
    """Each variant's estimated light; empty when none estimated one."""
    cells = []
    for variant in variants:
        path = run.path(asset_stage(variant), ENVMAP_FILE)
        if path.exists():
            estimate = EnvironmentMap.from_file(path).map.detach()
            height, width = estimate.shape[:2]
            label = f"estimated light ({LABELS.get(variant, variant)}): {width} x {height} px, shown bilinear"
            flash_path = run.path(asset_stage(variant), CAMERA_LIGHT_FILE)
            if flash_path.exists():  # the capture's flash, learned beside it (`refine.camera_light`)
                rgb = ", ".join(f"{float(x):.2f}" for x in CameraLight.load(flash_path).intensity)
                label += f"; with a flash at the camera on the flash photos (RGB {rgb}), left out when relit"
            cells.append(figures.image(f"envmap_{variant}", envmap_preview(as_shaded(estimate)), label, css="env"))
    if not cells:
        return ""
    return (
        "<h2>Estimated light</h2><p>Tone-mapped lat-long maps (up is the top row), determined only as far as the "
        "photos reveal it.</p><div>" + "".join(cells) + "</div>"
    )
