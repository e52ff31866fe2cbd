"""A run on a real capture, which has no ground-truth materials: how well it reproduces photos.

The only truth a capture has is its photos. Views the run never trained on (the dataset's test split:
every 8th frame of a capture without split lists) are the honest check. Each is scored inside the
object's mask (the run's object masks, or the dataset's own masks), where the asset is meant to be
right; the mask's share of the frame is reported beside it, so that a mask that shrank to nothing
cannot pass for a good score. Two renders per view:

  radiance   the Gaussian Splatting geometry with its view-dependent colours (what 3DGS reproduces)
  <variant>  each relightable asset shaded under the light it estimated (`envmap.exr`, and on a
             photo taken with a flash the flash it estimated, `camera_light.json`): the photo as the
             asset explains it, materials times light

Training views are scored the same way (how well the run fits what it saw).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data import View, load_run_scene
from matspray.data.images import linear_to_srgb, srgb_to_linear
from matspray.errors import DataError, RunError
from matspray.eval.evaluate import average_metrics, evaluate_images
from matspray.eval.lpips import load_lpips
from matspray.eval.page.paths import object_name
from matspray.geometry.evaluate import render_view
from matspray.geometry.ply import read_ply
from matspray.method.asset import ENVMAP_FILE, read_asset
from matspray.method.masks import read_object_masks
from matspray.method.refine.camera_light import lighting
from matspray.method.relight import render_relit
from matspray.metrics import gradient_energy
from matspray.presets import asset_stage
from matspray.render.backend import rendering_with
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir, write_json, write_text_atomic

RADIANCE = "radiance"  # the key of the geometry's own (view-dependent) colours
ENV_HEIGHT = 64  # rows of the prefiltered estimated light


@dataclass
class PhotoRenders:
    """What a run makes of one photo's camera: linear RGB [H, W, 3] per render (radiance, variants)."""

    view: View
    mask: Tensor  # [H, W] in [0, 1]: the object
    renders: dict[str, Tensor]


def view_masks(run: RunDir, views: list[View], split: str) -> dict[str, Tensor]:
    """The object mask [H, W] of each view: the run's masks stage (a capture without masks), else the dataset's."""
    if run.path("masks", "masks.pt").exists():
        masks = read_object_masks(run.path("masks")).masks[split]
        return {v.name: masks[v.name].float() for v in views}
    missing = [v.name for v in views if v.alpha is None]
    if missing:
        raise RunError(
            f"{run.root}: views {', '.join(missing[:3])} have no object mask (no masks stage and no "
            "alpha in the dataset); "
            "rerun `matspray run` on this run folder"
        )
    return {v.name: v.alpha.float() for v in views}


def estimated_lights(run: RunDir, variants: list[str], device) -> dict:
    """The prefiltered light each variant estimated (variants without one are left out)."""
    lights = {}
    for variant in variants:
        path = run.path(asset_stage(variant), ENVMAP_FILE)
        if path.exists():
            lights[variant] = EnvironmentMap.from_file(path, height=ENV_HEIGHT).to(device).prefilter()
    return lights


@dataclass
class RunRenderables:
    """What a run renders photos with, read once: the geometry, each variant's asset and its estimated light."""

    gaussians: object  # Gaussians
    assets: dict  # variant -> Asset
    lights: dict  # variant -> PrefilteredEnvironment (variants that estimated one)


def read_renderables(run: RunDir, device="cpu") -> RunRenderables:
    geometry_ply = run.path("geometry", "gaussians.ply")
    if not geometry_ply.exists():
        raise RunError(
            f"{run.root}: no Gaussian Splatting geometry (geometry/gaussians.ply); make it with `matspray run`"
        )
    variants = run.asset_variants()
    return RunRenderables(
        read_ply(geometry_ply)[0].to(device),
        {v: read_asset(run.path(asset_stage(v)), device=device) for v in variants},
        estimated_lights(run, variants, device),
    )


def photo_renders(
    run: RunDir,
    views: list[View],
    split: str,
    device="cpu",
    backend: str = "torch",
    progress: bool = True,
    renderables: RunRenderables | None = None,
    masks: dict[str, Tensor] | None = None,
) -> list[PhotoRenders]:
    """Render every view's camera with the geometry and with each asset under its own estimated light
    (`renderables`: the run's, read here when not given; `masks`: each view's object mask [H, W], the run's when not
    given)."""
    loaded = renderables or read_renderables(run, device)
    masks = view_masks(run, views, split) if masks is None else masks
    result = []
    with rendering_with(backend), torch.no_grad():
        for view in tqdm(
            views, desc=f"held-out photos ({split})" if split == "test" else f"photos ({split})", disable=not progress
        ):
            camera = view.camera.to(device)
            renders = {
                RADIANCE: srgb_to_linear(render_view(loaded.gaussians, camera).rgb.clamp(0, 1)).cpu()
            }  # its SH colours are sRGB
            for variant, light in loaded.lights.items():
                asset = loaded.assets[variant]
                flash = lighting(asset.camera_light, view.path)  # the flash refinement learned, on a flash photo
                rgb, alpha = render_relit(asset, camera, light, camera_light=flash)
                renders[variant] = (
                    rgb / alpha[..., None].clamp_min(1e-4)
                ).cpu()  # unpremultiplied: scored inside the mask
            result.append(PhotoRenders(view, masks[view.name], renders))
    return result


def score_photos(rendered: list[PhotoRenders], lpips) -> dict:
    """PSNR / SSIM / LPIPS inside the object mask per render (mean over views, and per view), the render's gradient
    energy as a share of the photo's in the same mask (`gradient_share`: below 1, softer than the photo), and each
    mask's coverage."""
    per_view, records = [], {}
    for item in rendered:
        if float(item.mask.sum()) < 1.0:
            raise DataError(
                f"view {item.view.name}: its object mask is empty, so the object cannot be scored there; "
                "check the object region (setting object_bounds) in the run's report"
            )
        record = {"view": item.view.name, "mask_coverage": float(item.mask.mean())}
        photo_energy = gradient_energy(linear_to_srgb(item.view.image.clamp(0, 1)), item.mask)
        for key, rgb in item.renders.items():
            record[key] = evaluate_images(rgb, item.view.image, item.mask, lpips)
            # the render's fine detail as a share of the photo's, compared as the metrics compare (sRGB-encoded)
            energy = gradient_energy(linear_to_srgb(rgb.clamp(0, 1)), item.mask)
            record[key]["gradient_share"] = energy / photo_energy if photo_energy > 0 else None
            records.setdefault(key, []).append(record[key])
        per_view.append(record)
    coverage = [r["mask_coverage"] for r in per_view]
    summary = {key: average_metrics(values) for key, values in records.items()}
    return {
        "summary": summary,
        "per_view": per_view,
        "views": len(per_view),
        "mask_coverage": {"mean": sum(coverage) / len(coverage), "min": min(coverage), "max": max(coverage)},
    }


def has_ground_truth(scene) -> bool:
    """Whether the dataset's test views have true material maps (a `matspray synth` object),
    as `matspray eval` scores."""
    return bool(scene.test) and all(v.path.with_name(f"{v.name}_basecolor.png").exists() for v in scene.test)


def evaluate_capture(
    run_dir,
    data=None,
    lpips_weights=None,
    device="cpu",
    backend: str = "torch",
    progress: bool = True,
    train_views: int = 8,
    scene=None,
) -> dict:
    """Score a run on its capture's held-out photos (and on up to `train_views` training photos); writes
    eval/heldout.json and returns the metrics."""
    run = RunDir(run_dir).require()
    identity = run.dataset()
    if scene is None:
        scene = load_run_scene(run, data)
    if [v.name for v in scene.train] != identity["train_views"]:
        raise DataError(f"{run.root}: this run was made from {identity['source']}, not from {scene.source}")
    if not scene.test:
        raise DataError(
            f"{identity['source']}: no held-out views (every photo was trained on); "
            "a capture without split lists holds out every 8th frame: give it 8 or more photos"
        )
    lpips, lpips_source = load_lpips(lpips_weights)
    loaded = read_renderables(run, device)
    stride = max(1, len(scene.train) // max(1, train_views))
    metrics = {
        "title": f"MatSpray on a capture without ground truth: {object_name(identity['source'])}",
        "lpips": lpips_source,
        "region": "inside the object mask (both images composited on white with it)",
        "heldout": score_photos(photo_renders(run, scene.test, "test", device, backend, progress, loaded), lpips),
        "train": score_photos(
            photo_renders(run, scene.train[::stride][:train_views], "train", device, backend, progress, loaded), lpips
        ),
    }
    write_json(run.path("eval", "heldout.json"), metrics)
    return metrics


def heldout_table(metrics: dict) -> str:
    """Markdown: PSNR / SSIM / LPIPS of every render on held-out and training photos, and the masks' coverage."""
    lines = [
        f"Scored {metrics['region']}.",
        "",
        "| render | held-out PSNR | SSIM | LPIPS | gradient energy share | training PSNR |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    held, train = metrics["heldout"]["summary"], metrics["train"]["summary"]

    def number(value, digits):
        return "n/a" if value is None else f"{value:.{digits}f}"

    for key in held:
        label = "geometry (3DGS colours)" if key == RADIANCE else f"{key} asset, its estimated light"
        lines.append(
            f"| {label} | {number(held[key]['psnr'], 2)} | {number(held[key]['ssim'], 3)} | "
            f"{number(held[key]['lpips'], 3)} | {format_share(held[key].get('gradient_share'))} "
            f"| {number(train.get(key, {}).get('psnr'), 2)} |"
        )
    cover = metrics["heldout"]["mask_coverage"]
    lines += [
        "",
        f"{metrics['heldout']['views']} held-out views; the object mask covers {100 * cover['mean']:.1f}% of a view on "
        f"average ({100 * cover['min']:.1f}% to {100 * cover['max']:.1f}%).",
    ]
    return "\n".join(lines) + "\n"


def format_share(value: float | None) -> str:
    """A gradient energy share in two significant digits (0.95, 0.012: a very soft render still reads as a number)."""
    return "n/a" if value is None else f"{value:.2g}"


def write_heldout_table(path: Path, metrics: dict) -> None:
    write_text_atomic(Path(path), heldout_table(metrics))
