"""`matspray eval --glb FILE.glb`: an exported mesh against the truth of a `matspray synth` object.

The mesh is read by the glTF reader and turned into Mitsuba parts exactly as `synth --asset` does
(`matspray.synth.gltf_object.asset_parts`, placement 'keep'), path traced under each held-out light at
the test cameras, and ray cast for its material maps (`cast_ground_truth`, the maps `synth` writes as
truth). Relighting and material PSNR / SSIM / LPIPS are scored beside the Gaussian asset's (when the
run the file was exported from is known) and written with side-by-side pictures to FILE_eval/. Both
are scored by `score_renders` with their own alpha, under the object mask (GT) and over the union of
the silhouettes ("_union" keys), and under the same held-out lights."""

from __future__ import annotations

import html
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from matspray.data import View, load_run_scene, load_scene, read_image
from matspray.data.formats.blender import read_scene_json
from matspray.errors import ConfigError, file_error
from matspray.eval.lpips import load_lpips
from matspray.eval.page.markup import Figures, html_page, markdown_to_html
from matspray.eval.page.paths import page_places
from matspray.eval.run_eval import (
    GroundTruth,
    ViewRenders,
    asset_renders,
    check_synthetic,
    load_relight_lights,
    read_view_truth,
    relight_env_names,
    score_renders,
)
from matspray.eval.tables import UNION, UNION_LABEL, material_table
from matspray.export.frames import GLTF_FROM_DATASET, transform_directions, transform_points
from matspray.gltf.read import read_gltf
from matspray.method.asset import read_asset
from matspray.presets import VARIANT_NAMES, asset_stage
from matspray.render.backend import rendering_with
from matspray.rundir import RunDir, write_json, write_text_atomic
from matspray.synth.gltf_object import asset_parts
from matspray.synth.groundtruth import cast_ground_truth
from matspray.synth.mitsuba_scene import build_scene, render_view, select_variant

DEFAULT_SPP = 64
FRAMES = ("gltf", "dataset")
REPORT_VIEWS = 3


def read_glb_parts(path, frame: str | None = None):
    """Mitsuba parts and textures of an exported file in the dataset's world, and its `matspray` extras.
    `frame` (gltf | dataset) overrides the frame the file's extras state (gltf when they say none)."""
    asset = read_gltf(path)
    extras = asset.extras.get("matspray", {}) if isinstance(asset.extras.get("matspray"), dict) else {}
    if frame is not None and frame not in FRAMES:
        raise ConfigError(f"unknown frame '{frame}'; choose gltf or dataset")
    # what `matspray export` wrote into the file's extras; a damaged or hand-edited value is named here, before any work
    for key, valid, wanted, hint in (
        ("frame", FRAMES, "gltf or dataset", "pass --frame gltf or --frame dataset"),
        ("variant", VARIANT_NAMES, "a variant's name", "fix the extras or re-export the file"),
        ("run", None, "a run folder", "fix the extras, or pass --run and --data"),
    ):
        value = extras.get(key)
        if value is not None and (
            not isinstance(value, str) or not value or "\0" in value or valid is not None and value not in valid
        ):
            raise file_error(path, f"asset.extras.matspray.{key} is {json.dumps(value)[:60]}, not {wanted}", hint)
    frame = frame or extras.get("frame") or "gltf"
    if frame == "dataset":  # bring the file into glTF's frame, which the reader maps to the dataset's world
        asset = replace(
            asset,
            primitives=[
                replace(
                    p,
                    positions=transform_points(GLTF_FROM_DATASET, p.positions),
                    normals=None if p.normals is None else transform_directions(GLTF_FROM_DATASET, p.normals),
                )
                for p in asset.primitives
            ],
        )
    parts, textures, _ = asset_parts(asset, placement="keep")
    return parts, textures, extras


def mesh_renders(
    parts, textures, views: list[View], envs: dict[str, np.ndarray], spp: int, progress: bool = True
) -> list[ViewRenders]:
    """Mitsuba's path-traced renders of the mesh under each light [H, 2H, 3] and its ray-cast material maps."""
    select_variant()
    bar = tqdm(total=len(views) * (len(envs) + 1), desc="eval --glb", unit="render", disable=not progress)
    relit: list[dict] = [{} for _ in views]
    maps, alphas = [], []
    for light_index, (env, values) in enumerate(envs.items()):
        scene = build_scene(parts, textures, values)
        if light_index == 0:
            for view in views:
                truth = cast_ground_truth(scene, textures, view.camera)
                maps.append(truth)
                alphas.append(torch.from_numpy(truth.coverage))
                bar.update()
        for index, view in enumerate(views):
            rgb, _ = render_view(scene, view.camera, spp, seed=index)
            relit[index][env] = torch.from_numpy(rgb)
            bar.update()
    bar.close()
    return [
        ViewRenders(
            r,
            torch.from_numpy(m.base_color).clamp(0, 1),
            torch.from_numpy(m.roughness).clamp(0, 1),
            torch.from_numpy(m.metallic).clamp(0, 1),
            a,
        )
        for r, m, a in zip(relit, maps, alphas)
    ]


def dataset_spp(data: Path) -> int:
    """The samples per pixel the dataset's truth was rendered with (scene.json), else DEFAULT_SPP."""
    settings = (read_scene_json(Path(data)) or {}).get("settings")
    return int(settings.get("spp", DEFAULT_SPP)) if isinstance(settings, dict) else DEFAULT_SPP


def evaluate_glb(
    glb,
    data=None,
    run=None,
    variant: str | None = None,
    frame: str | None = None,
    lpips_weights=None,
    spp: int | None = None,
    out=None,
    progress: bool = True,
    device="cpu",
    backend: str = "torch",
) -> dict:
    """Score `glb` (and the Gaussian asset it came from, when its run is found) on the dataset's test
    views; writes metrics.json, tables.md and report.html into `out` (default FILE_eval/ beside it). Mitsuba
    renders the mesh; the Gaussian asset renders on `device` with the rasterizer `backend` (both resolved)."""
    glb = Path(glb)
    if not glb.is_file():
        raise ConfigError(f"{glb}: no such file; make one with `matspray export`")
    parts, textures, extras = read_glb_parts(glb, frame)
    run = (
        Path(run)
        if run is not None
        else (Path(extras["run"]) if extras.get("run") and Path(extras["run"], "dataset.json").exists() else None)
    )
    variant = variant or extras.get("variant", "full")
    if data is None:
        if run is None:
            raise ConfigError(f"{glb}: which dataset? pass --data (the file does not name a run to take it from)")
        data = RunDir(run).dataset()["source"]
    data = Path(data)
    scene = load_run_scene(RunDir(run), data) if run is not None else load_scene(data)
    check_synthetic(scene)
    views = scene.test
    truths = [read_view_truth(v) for v in views]
    env_names = sorted(set.intersection(*(set(relight_env_names(v)) for v in views)))
    if not env_names:
        raise ConfigError(
            f"{data}: no relit ground truth (test/*_relight_*.png): make the object with `matspray synth`"
        )
    envs = {name: read_image(data / "envmaps" / f"{name}.exr")[0].numpy() for name in env_names}
    lpips, lpips_source = load_lpips(lpips_weights)
    start = time.perf_counter()
    renders = mesh_renders(parts, textures, views, envs, spp or dataset_spp(data), progress)
    metrics = {
        "glb": str(glb),
        "data": str(data),
        "lpips": lpips_source,
        "relight_envs": env_names,
        "frame": frame or extras.get("frame") or "gltf",
        "faces": int(sum(len(p.faces) for p in parts)),
        "render_seconds": round(time.perf_counter() - start, 2),
        "mesh": score_renders(renders, views, truths, env_names, lpips),
    }
    gaussian_renders = None
    if run is not None and (run / asset_stage(variant) / "asset.ply").exists():
        asset = read_asset(run / asset_stage(variant), device=device)
        lights = load_relight_lights(data, env_names, device)
        with rendering_with(backend):
            gaussian_renders = [asset_renders(asset, view, lights) for view in views]
        metrics["gaussians"] = score_renders(gaussian_renders, views, truths, env_names, lpips)
        metrics["run"], metrics["variant"] = str(run), variant
    out = Path(out) if out is not None else glb.with_name(f"{glb.stem}_eval")
    write_json(out / "metrics.json", metrics)
    text = glb_tables(metrics)
    write_text_atomic(out / "tables.md", text)
    write_glb_report(out, metrics, text, views, truths, renders, gaussian_renders)
    return metrics


def glb_tables(metrics: dict) -> str:
    methods = {"Mesh (Mitsuba)": metrics["mesh"]["summary"]}
    if "gaussians" in metrics:
        methods = {"Gaussians": metrics["gaussians"]["summary"], **methods}
    lines = [
        f"# Exported mesh: {Path(metrics['glb']).name} ({metrics['faces']} faces)",
        "",
        f"Held-out lights: {', '.join(metrics['relight_envs'])}; LPIPS: {metrics['lpips']}.",
        "",
        material_table(methods),
    ]
    if "gaussians" in metrics:
        lines += ["", relighting_gap_line(metrics["gaussians"]["summary"], metrics["mesh"]["summary"])]
    return "\n".join(lines) + "\n"


def relighting_gap_line(gaussians: dict, mesh: dict) -> str:
    """How far the mesh's relighting PSNR is below the Gaussian asset's, under both figures (same lights,
    same truth): the object-mask (GT) gap hides what the mesh gets wrong at its silhouette, the union
    gap counts it, so the union gap is the honest mesh-against-Gaussians comparison."""
    parts = []
    for key, label in (("relighting", "object mask (GT)"), (f"relighting{UNION}", UNION_LABEL)):
        if key in gaussians and key in mesh:
            gap = gaussians[key]["psnr"] - mesh[key]["psnr"]
            parts.append(f"{gap:.2f} dB under the {label}")
    return f"Relighting PSNR of the mesh is below the Gaussian asset's by {' and '.join(parts)} (negative: above)."


def write_glb_report(
    out: Path,
    metrics: dict,
    tables: str,
    views: list[View],
    truths: list[GroundTruth],
    mesh: list[ViewRenders],
    gaussians: list[ViewRenders] | None,
) -> Path:
    """report.html: per test view and light, the truth, the Gaussian asset and the mesh side by side."""
    figures = Figures(out / "report")
    sections = [
        f"<h1>Exported mesh: {html.escape(Path(metrics['glb']).name)}</h1>",
        "<p><i>Truth</i>: Mitsuba's render of the true object. <i>Gaussians</i>: the asset, split-sum shaded. "
        "<i>Mesh</i>: the exported glTF file, path traced by Mitsuba exactly like the truth.</p>",
    ]
    for index, (view, truth) in enumerate(list(zip(views, truths))[:REPORT_VIEWS]):
        sections.append(f"<h2>Test view {html.escape(view.name)}</h2>")
        for env in metrics["relight_envs"]:
            cells = [figures.image(f"{view.name}_{env}_truth", truth.relit[env], f"truth, {env}", truth.mask)]
            if gaussians is not None:
                cells.append(
                    figures.image(
                        f"{view.name}_{env}_gaussians",
                        gaussians[index].relit[env],
                        f"Gaussians, {env}",
                        gaussians[index].alpha,
                    )
                )
            cells.append(
                figures.image(f"{view.name}_{env}_mesh", mesh[index].relit[env], f"mesh, {env}", mesh[index].alpha)
            )
            sections.append("<div>" + "".join(cells) + "</div>")
    sections.append(markdown_to_html(tables))
    path = out / "report.html"
    write_text_atomic(path, html_page(sections, "MatSpray export", page_places(out)))
    return path
