"""Which Gaussians the web page draws. In software WebGL a frame's time is the splats' fragments, and a trained
asset stacks dozens of footprints on each pixel, many of which add next to nothing to it: faint, large, or behind
the surface in most views. `page_gaussians` ranks the Gaussians by the colour they give per pixel of footprint on the
page's orbit and leaves out the least of them, as many as keeps the asset's relit frames within a PSNR of the whole
asset's inside the object (docs/dev/web.md measures both sides of the trade)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb
from matspray.gaussians import Gaussians
from matspray.method.asset import Asset
from matspray.method.relight import render_relit, spec_cameras
from matspray.metrics import psnr_from_mse
from matspray.render.projection import footprint_eigenvalues, log_opacity_ratio, project_gaussians
from matspray.render.raster.gbuffer import rendered_weights
from matspray.render.settings import RasterSettings
from matspray.web import DEFAULT_WEB_PSNR
from matspray.web.page import page_view

RANKED_VIEWS = 12  # orbit views the ranking sums over; the check renders 6 others, between them
RESOLUTION = 256  # pixels of those views, under the page's 512: the ranking is a ratio of pixel counts
BISECTIONS = 7  # halvings of the share of footprint left out (1/128 of MOST_LEFT_OUT at the end)
MOST_LEFT_OUT = 0.8  # the most of the summed footprint the bisection tries (docs/dev/web.md: what 0.6 costs)
# besides the asset's own light: of the packaged lights, the one under which leaving Gaussians out showed most on the
# demo's asset (small bright lamps: sharp highlights; docs/dev/web.md)
CHECK_LIGHT = "studio-small"


@dataclass(frozen=True)
class PageDetail:
    keep: Tensor  # [N] bool: the Gaussians the page draws
    left_out: float  # the share of the Gaussians' summed footprint (page pixels, the ranking views) left out
    psnr: float  # the kept Gaussians' relit frames against the whole asset's (inf when every one is kept)


def footprint_areas(gaussians: Gaussians, camera: Camera, settings: RasterSettings = RasterSettings()) -> Tensor:
    """Pixels of the rectangle the page draws each Gaussian in [N] (src/shaders.js PROJECT_FRAGMENT: the ellipse's
    bounding rectangle along its axes where alpha reaches the cutoff, half a pixel added to each half side; 0 for a
    Gaussian it does not draw)."""
    g = gaussians.detach()
    proj = project_gaussians(
        g.means, g.scaled_axes(), camera.viewmat, camera.K, camera.width, camera.height, settings.near, settings.eps2d
    )
    major, minor = footprint_eigenvalues(proj.cov2d)  # [N] each
    reach = 2.0 * log_opacity_ratio(g.opacities, settings.min_alpha)  # [N] variances where alpha meets the cutoff
    half_major = torch.sqrt(reach * major) + 0.5
    half_minor = torch.sqrt(reach * minor) + 0.5
    drawn = proj.valid & (reach > 0)
    return torch.where(drawn, 4.0 * half_major * half_minor, torch.zeros_like(major))


def colour_per_pixel(gaussians: Gaussians, cameras: list[Camera]) -> tuple[Tensor, Tensor]:
    """Each Gaussian's blending weight summed over the cameras' images (pixels' worth) [N], and its footprint's
    pixels summed over them [N]."""
    weights = torch.zeros(len(gaussians), dtype=torch.float64)
    areas = torch.zeros(len(gaussians), dtype=torch.float64)
    for camera in cameras:
        weights += rendered_weights(gaussians, camera).detach().cpu().double()
        areas += footprint_areas(gaussians, camera).cpu().double()
    return weights, areas


def drop_order(weights: Tensor, areas: Tensor) -> tuple[Tensor, Tensor]:
    """The Gaussians from the least colour per pixel of footprint to the most [N] (those never drawn first), and
    the share of the summed footprint left out once each and all before it are [N]."""
    value = torch.where(areas > 0, weights / areas.clamp_min(1e-12), torch.zeros_like(weights))
    order = torch.argsort(value, stable=True)
    shares = torch.cumsum(areas[order], 0) / areas.sum().clamp_min(1e-12)
    return order, shares


def kept(order: Tensor, shares: Tensor, left_out: float) -> Tensor:  # -> [N] bool
    keep = torch.ones(len(order), dtype=torch.bool)
    keep[order[shares <= left_out]] = False
    return keep


def subset(asset: Asset, keep: Tensor) -> Asset:
    visibility = None if asset.visibility is None else asset.visibility[keep]
    return Asset(asset.gaussians.subset(keep), asset.materials[keep], asset.normals[keep], visibility)


def srgb_frame(asset: Asset, camera: Camera, light, background: Tensor) -> tuple[Tensor, Tensor]:
    """The asset relit, sRGB over the page's background [H, W, 3], and its coverage [H, W]."""
    with torch.no_grad():
        rgb, alpha = render_relit(asset, camera, light, background)
    return linear_to_srgb(rgb).clamp(0, 1), alpha


def frames_psnr(
    asset: Asset, references: list[tuple[Tensor, Tensor]], cameras: list[Camera], light, background
) -> float:
    """PSNR of the asset's relit frames against `references` [(sRGB frame, coverage)], over the pixels the
    references' object covers (coverage above one half), pooled over the cameras."""
    squared, pixels = 0.0, 0
    for camera, (reference, coverage) in zip(cameras, references):
        inside = coverage > 0.5
        squared += float((srgb_frame(asset, camera, light, background)[0] - reference)[inside].square().sum())
        pixels += 3 * int(inside.sum())
    return psnr_from_mse(squared / max(pixels, 1))


def page_gaussians(
    asset: Asset, view: dict, lights: list, background: Tensor, min_psnr: float = DEFAULT_WEB_PSNR, progress=False
) -> PageDetail:
    """The Gaussians the page of `asset` draws: the most left out (of the least colour per pixel of footprint first)
    whose relit frames under each of `lights` (prefiltered) stay at `min_psnr` or above against the whole asset's
    inside the object, on the page's orbit `view` (`web.page.page_view`). `min_psnr` inf keeps every Gaussian."""
    if math.isinf(min_psnr):
        return PageDetail(torch.ones(len(asset.gaussians), dtype=torch.bool), 0.0, math.inf)
    cameras = spec_cameras(page_view(view, RESOLUTION), 2 * RANKED_VIEWS)
    ranking, checks = cameras[0::2], cameras[1::4]
    order, shares = drop_order(*colour_per_pixel(asset.gaussians, ranking))
    references = [[srgb_frame(asset, camera, light, background) for camera in checks] for light in lights]

    def worst(share: float) -> float:  # the lowest PSNR over the lights with `share` of the footprint left out
        drawn = subset(asset, kept(order, shares, share))
        return min(frames_psnr(drawn, frames, checks, light, background) for light, frames in zip(lights, references))

    low, high, psnr = 0.0, MOST_LEFT_OUT, None
    for _ in tqdm(range(BISECTIONS), desc="web page: Gaussians to draw", disable=not progress):
        share = 0.5 * (low + high)
        value = worst(share)
        if value >= min_psnr:
            low, psnr = share, value
        else:
            high = share
    if psnr is None:  # only what no view draws goes: its frames' PSNR at that
        psnr = worst(0.0)
    return PageDetail(kept(order, shares, low), low, psnr)
