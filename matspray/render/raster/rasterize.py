"""Differentiable Gaussian rasterization: any per-Gaussian features to an image, as 3DGS blends them.

    features[p] = sum_k w_k f_k + (1 - alpha[p]) * background,   w_k = alpha_k prod_{j<k} (1 - alpha_j)
    alpha_k     = min(max_alpha, opacity_k * exp(-0.5 d^T conic_k d)),   d = pixel centre - projected mean

over the Gaussians covering pixel p sorted front to back by the camera z of their centres. As in 3DGS,
hits with alpha_k < min_alpha are skipped and blending stops before the transmittance would fall below
min_transmittance.

Backend `torch` is a pair-list design: the (Gaussian, pixel) pairs whose pixel centre lies inside the
Gaussian's footprint ellipse (enumerated row span by row span), one integer sort by pixel then depth,
then `blend_hits`: transmittance by a segmented cumulative sum of log(1 - alpha) in float64, weights
scattered with `index_add`, and a hand-written backward pass. It is the readable reference.

Backend `numba` (CPU; matspray.render.numba.backend, docs/dev/rasterizer.md) computes the projection, footprints and
depth order of `_setup` below with the same float32 arithmetic in compiled code, with a hand-written backward,
and blends the same hits in compiled 16 x 16 tile loops; tests/test_numba_backend.py holds it to this one within
1e-5 (images) and 1e-4 (gradients).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.backend import active_backend, note_render, resolve_backend
from matspray.render.blend import blend_hits, hit_weights
from matspray.render.compositing import ray_major_order
from matspray.render.output import RasterOutput
from matspray.render.pairs import EMPTY_BOX, box_areas, clip_rows, ellipse_pixel_pairs, pixel_boxes, row_bands
from matspray.render.projection import log_opacity_ratio, max_eigen_radius, project_gaussians
from matspray.render.raster.gsplat import rasterize_gsplat
from matspray.render.settings import RasterSettings


def rasterize(
    gaussians: Gaussians,
    camera: Camera,
    features: Tensor,  # [N, C]
    background: Tensor | None = None,  # [C]; None means zeros
    *,
    backend: str | None = None,
    settings: RasterSettings = RasterSettings(),
    max_pairs: int = 1 << 23,
    absgrad: bool = False,
) -> RasterOutput:
    """Render per-Gaussian `features` into `camera`; differentiable w.r.t. the Gaussians' means,
    log_scales, quats, opacity_logits and w.r.t. `features`.

    `backend`: torch (ours, the reference), numba (ours, compiled, CPU), gsplat (CUDA, optional extra) or auto
    (see matspray.render.backend); None takes the one of the enclosing `rendering_with` block (torch outside any).
    `absgrad`: backward also computes, per Gaussian, the sum over pixels of |d loss_pixel / d means2d|
    (gsplat's absgrad, which its densification strategy can use), read as `RasterOutput.screen_absgrads`.
    `max_pairs` bounds the (Gaussian, pixel) candidate pairs processed at once by backend torch: larger images
    are rendered in bands of rows (the autograd graph still keeps every band until backward). Backend numba
    keeps no pair list (one gradient row per (16 x 16 tile, Gaussian) instead) and ignores it.
    """
    n = len(gaussians)
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"rasterize: features must be [N={n}, C], got {tuple(features.shape)}")
    if background is not None and tuple(background.shape) != (features.shape[1],):
        raise ValueError(f"rasterize: background must be [C={features.shape[1]}], got {tuple(background.shape)}")
    chosen = resolve_backend(active_backend() if backend is None else backend, gaussians.device)
    note_render(chosen)
    if chosen == "gsplat":
        return rasterize_gsplat(gaussians, camera, features, background, settings, absgrad)
    if chosen == "numba":
        return _rasterize_numba(gaussians, camera, features, background, settings, absgrad)
    return _rasterize_torch(gaussians, camera, features, background, settings, max_pairs, absgrad)


def depth_ranks(depths: Tensor) -> Tensor:  # [N] -> [N] long: 0 for the nearest centre
    # stable: equal depths (a thousand pairs among 100 000 float32 depths) keep index order, as backend numba's
    # radix sort does, so both blend the same hits in the same order
    order = torch.argsort(depths, stable=True)
    ranks = torch.empty_like(order)
    ranks[order] = torch.arange(len(order), device=depths.device)
    return ranks


@dataclass
class _Setup:
    proj: object  # ProjectedGaussians
    opacities: Tensor  # [N]
    boxes: Tensor  # [N, 4] pixel boxes of the footprints (empty when not drawn)
    radii: Tensor  # [N]
    ranks: Tensor  # [N] front-to-back order of the centres
    footprints: tuple  # projected centres, conics, footprint radius^2 (no grad)

    @property
    def splats(self) -> Tensor:  # [6, N] projected mean x, y; conic a, b, c; opacity
        proj = self.proj
        return torch.stack([*proj.means2d.unbind(-1), *proj.conics.unbind(-1), self.opacities])


def _setup(gaussians: Gaussians, camera: Camera, settings: RasterSettings) -> _Setup:
    """Project the Gaussians and find each one's footprint (what every rendering of a view starts with)."""
    height, width = camera.height, camera.width
    min_alpha = settings.min_alpha
    proj = project_gaussians(
        gaussians.means, gaussians.scaled_axes(), camera.viewmat, camera.K, width, height, settings.near, settings.eps2d
    )
    opacities = gaussians.opacities
    with torch.no_grad():
        # where opacity * exp(-q / 2) >= min_alpha: q <= radius2; the small margin keeps every true hit,
        # the exact alpha test below decides
        radius2 = 2.0 * log_opacity_ratio(opacities, min_alpha) + 1e-3
        half = torch.sqrt(radius2[:, None] * proj.cov2d[:, [0, 2]])
        boxes = pixel_boxes(proj.means2d - half, proj.means2d + half, width, height, centres=True)
        drawable = proj.valid & (opacities >= min_alpha)
        boxes[~drawable] = torch.tensor(EMPTY_BOX, device=boxes.device)
        radii = torch.where(box_areas(boxes) > 0, max_eigen_radius(proj.cov2d), torch.zeros_like(opacities))
        ranks = depth_ranks(proj.depths)
        footprints = (proj.means2d.detach(), proj.conics.detach(), radius2)
    return _Setup(proj, opacities, boxes, radii, ranks, footprints)


@torch.no_grad()
def view_weights(
    gaussians: Gaussians,
    camera: Camera,
    *,
    settings: RasterSettings = RasterSettings(),
    max_pairs: int = 1 << 23,
) -> tuple[Tensor, Tensor, Tensor]:
    """The blending weights of every (Gaussian, pixel) hit `rasterize` would blend for this camera:
    Gaussian ids [M], row-major pixel ids [M], weights [M]. For frozen geometry, rendering any
    features [N, C] is then `zeros(H * W, C).index_add_(0, pixel_ids, weights[:, None] * f[gaussian_ids])`."""
    note_render("torch")  # the weights are the torch backend's, whatever the run's rasterizer
    setup = _setup(gaussians, camera, settings)
    splats, width = setup.splats, camera.width
    parts = []
    for row_start, row_end in row_bands(setup.boxes, camera.height, max_pairs):
        gaussian_ids, pixel_ids = _candidate_pairs(
            clip_rows(setup.boxes, row_start, row_end), setup.footprints, setup.ranks, row_start, width
        )
        ids, pixels, weights = hit_weights(
            splats, gaussian_ids, pixel_ids, width, row_start, (row_end - row_start) * width, settings
        )
        parts.append((ids, pixels + row_start * width, weights))
    return tuple(torch.cat(column) for column in zip(*parts))


def _rasterize_torch(gaussians, camera, features, background, settings: RasterSettings, max_pairs: int, absgrad: bool):
    height, width = camera.height, camera.width
    setup = _setup(gaussians, camera, settings)
    proj, opacities, boxes, radii, ranks, footprints = (
        setup.proj,
        setup.opacities,
        setup.boxes,
        setup.radii,
        setup.ranks,
        setup.footprints,
    )
    splats = setup.splats  # [6, N]
    values = torch.cat([features.t(), proj.depths[None], torch.ones_like(opacities)[None]])  # [C + 2, N]
    bands, num_hits = [], 0
    for row_start, row_end in row_bands(boxes, height, max_pairs):
        gaussian_ids, pixel_ids = _candidate_pairs(
            clip_rows(boxes, row_start, row_end), footprints, ranks, row_start, width
        )
        band, blended = blend_hits(
            splats,
            values,
            gaussian_ids,
            pixel_ids,
            width,
            row_start,
            (row_end - row_start) * width,
            settings,
            absgrad_of=proj.means2d if absgrad else None,
        )
        bands.append(band.reshape(row_end - row_start, width, -1))
        num_hits += blended
    image = torch.cat(bands, dim=0) if len(bands) > 1 else bands[0]  # [H, W, C + 2]
    return _output(image, background, proj.means2d, radii, "torch", num_hits)


def _rasterize_numba(gaussians, camera, features, background, settings: RasterSettings, absgrad: bool):
    """Projection, footprints, depth order and blending all compiled (matspray.render.numba.backend): the same
    float32 projection as `_setup`, the same hits as the pair list."""
    from matspray.render.numba.backend import rasterize_gaussians  # imports numba: only when this backend runs

    image, num_hits, means2d, radii = rasterize_gaussians(gaussians, camera, features, settings, absgrad)
    return _output(image, background, means2d, radii, "numba", num_hits)


def _output(image, background, means2d, radii, backend: str, num_hits: int) -> RasterOutput:
    """RasterOutput from the blended [H, W, C + 2] image (features, accumulated depth, alpha)."""
    alpha = image[..., -1]
    colour = image[..., :-2]
    if background is not None:
        colour = colour + (1.0 - alpha)[..., None] * background.to(colour)
    return RasterOutput(
        features=colour,
        alpha=alpha,
        depth=image[..., -2],
        means2d=means2d.detach(),
        radii=radii,
        backend=backend,
        screen=means2d,
        pixel_hits=num_hits,
    )


def _candidate_pairs(boxes, footprints, ranks, row_start, width):
    """(Gaussian, pixel) pairs whose pixel centre lies inside the Gaussian's footprint ellipse, within
    the rows of `boxes`: Gaussian ids [M] and pixel ids [M] counted from `row_start`, sorted by pixel
    and then front to back. Integer bookkeeping only, no autograd."""
    with torch.no_grad():
        centres, conics, radius2 = footprints
        owner, pixel_ids = ellipse_pixel_pairs(boxes, centres, conics, radius2, width)
        pixel_ids = pixel_ids - row_start * width
        order = ray_major_order(pixel_ids, ranks.index_select(0, owner), len(ranks))
        return owner.index_select(0, order), pixel_ids.index_select(0, order)
