"""Rendering views of trained Gaussians (sRGB colour, alpha, normals, depth) and novel-view metrics."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray import metrics
from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb, read_raw, resize, srgb_to_linear, write_image, write_raw
from matspray.data.scene import View
from matspray.gaussians import Gaussians
from matspray.geometry.normals import angular_error_degrees, normal_map_to_rgb, oriented_normals
from matspray.render.output import RasterOutput
from matspray.render.raster.rasterize import rasterize
from matspray.render.shade.sh import sh_colors


@dataclass
class ViewRender:
    rgb: Tensor  # [H, W, 3] sRGB-encoded colour composited over the background (not clamped)
    alpha: Tensor  # [H, W]
    normals: Tensor  # [H, W, 3] world-space blended normals (unit where covered, else 0)
    depth: Tensor  # [H, W] expected camera z (0 where nothing is covered)
    raster: RasterOutput  # the rasterizer's full output (screen-space means, radii)


def render_view(
    gaussians: Gaussians,
    camera: Camera,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    absgrad: bool = False,
) -> ViewRender:
    """Colour and normals in one rasterization. The Gaussians' SH give sRGB-encoded colour, as in
    3DGS, so that 3DGS viewers show the PLY with the right colours; `background` [3] is sRGB too. `absgrad`: also
    collect the absolute screen-space gradients (RasterOutput.screen_absgrads) that densification may use."""
    colours = sh_colors(gaussians, camera, sh_degree)
    normals = oriented_normals(gaussians, camera)
    if background is None:
        background = torch.zeros(3, device=gaussians.device)
    background = torch.cat([background.to(colours), torch.zeros(3, dtype=colours.dtype, device=colours.device)])
    out = rasterize(gaussians, camera, torch.cat([colours, normals], dim=1), background, absgrad=absgrad)
    return ViewRender(
        rgb=out.features[..., :3],
        alpha=out.alpha,
        normals=F.normalize(out.features[..., 3:], dim=-1),
        depth=out.expected_depth,
        raster=out,
    )


def target_srgb(view: View, background: Tensor) -> Tensor:  # -> [H, W, 3] the photo in sRGB over `background`
    rgb = linear_to_srgb(view.image)
    if view.alpha is None:
        return rgb
    alpha = view.alpha[..., None]
    return rgb * alpha + background.to(rgb) * (1 - alpha)


def evaluation_background(view: View) -> Tensor:  # -> [3] sRGB
    """What a render of `view` is composited on to be compared with its photo. With a mask, white: the photo is
    composited on white too, so only the object counts. Without one, the whole photo is the target, and a part of
    the backdrop that no training view saw (alpha 0) shows this colour: it must be the one training composited on
    (`step.training_losses`: black), or a dark backdrop turns white in views that did not see it."""
    device = view.image.device
    return torch.ones(3, device=device) if view.alpha is not None else torch.zeros(3, device=device)


def psnr(pred: Tensor, target: Tensor, weights: Tensor | None = None) -> float:
    """PSNR (dB) of [H, W, C] values clamped to [0, 1]; `weights` [H, W] restrict the pixels."""
    return metrics.psnr(pred.detach().clamp(0, 1), target.clamp(0, 1), weights)


def true_normals(view: View) -> Tensor | None:
    """World-space ground-truth normals [H, W, 3] from `{name}_normal.exr` next to the view's image
    (the layout `matspray synth` writes), resized to the view; None when there is no such file."""
    if view.path is None:
        return None
    path = Path(view.path).with_name(f"{view.name}_normal.exr")
    if not path.exists():
        return None
    normals = read_raw(path)[..., :3].float()
    if normals.shape[:2] != (view.height, view.width):
        normals = resize(normals, view.height, view.width)
    return F.normalize(normals, dim=-1)


def evaluate_views(
    gaussians: Gaussians,
    views: list[View],
    sh_degree: int | None = None,
    out_dir=None,
    background: Tensor | None = None,
) -> dict:
    """Novel-view metrics of `views`; with `out_dir`, writes renders/{view}.png (colour over the view's
    background, `evaluation_background`) and normals/{view}.png ((n + 1) / 2, world space) there.

    psnr: whole image, the render over the view's background against the photo (composited on white where it has
    a mask). psnr_masked: only the object's pixels (weighted by the true alpha). normal_error_deg: mean angle between
    rendered and true normals on the object (where `{view}_normal.exr` exists; uncovered pixels count as 90
    degrees). `background` [3] sRGB: one colour for every view instead (what `benchmarks.heldout_background`
    compares)."""
    device = gaussians.means.device
    per_view = {}
    for view in views:
        view = view.to(device)  # the photo, its mask and the true normals are compared where the render is
        over = (evaluation_background(view) if background is None else background).to(device)
        with torch.no_grad():
            render = render_view(gaussians, view.camera, sh_degree, over)
        target = target_srgb(view, over)
        entry = {"psnr": psnr(render.rgb, target)}
        if view.alpha is not None and float(view.alpha.sum()) > 0:
            entry["psnr_masked"] = psnr(render.rgb, target, view.alpha)
        normals = true_normals(view)
        if normals is not None:
            normals = normals.to(device)
            on_object = (view.alpha > 0.5) if view.alpha is not None else (normals.norm(dim=-1) > 0.5)
            if bool(on_object.any()):
                entry["normal_error_deg"] = float(angular_error_degrees(render.normals, normals)[on_object].mean())
        per_view[view.name] = entry
        if out_dir is not None:
            out_dir = Path(out_dir)
            write_image(out_dir / "renders" / f"{view.name}.png", srgb_to_linear(render.rgb.clamp(0, 1)))
            write_raw(
                out_dir / "normals" / f"{view.name}.png",
                normal_map_to_rgb(render.normals) * (render.alpha[..., None] > 0),
            )
    summary = {"views": per_view}
    for key in ("psnr", "psnr_masked", "normal_error_deg"):
        values = [v[key] for v in per_view.values() if key in v]
        summary[key] = sum(values) / len(values) if values else None
    return summary
