"""gsplat's own `rasterization()` on the CPU, for tests: its four CUDA entry points replaced by torch code.

`gsplat.rendering.rasterization` (gsplat 1.5.3, the version this was written against; pyproject's `test`
extra pins the range) is pure Python around four CUDA calls it binds by name in `gsplat.rendering`:
`fully_fused_projection`, `isect_tiles`, `isect_offset_encode`, `rasterize_to_pixels`. `gsplat_on_cpu`
swaps them for
  - gsplat's own pure-torch references (`gsplat.cuda._torch_impl`) where they exist: projection
    (`_fully_fused_projection`, after `_quat_scale_to_covar_preci`), tile intersection (`_isect_tiles`) and
    tile offsets (`_isect_offset_encode`);
  - what the references leave out, written here after the CUDA source (cuda/csrc, 1.5.3):
    ProjectionEWA3DGSFused.cu's culling and opacity-aware integer radii per axis, and
    RasterizeToPixels3DGSFwd.cu's per-pixel blending (the hits of the pixel's 16x16 tile in their sorted
    order; pixel centre at +0.5; sigma = 0.5 (a dx^2 + c dy^2) + b dx dy; a hit is skipped when sigma < 0
    or alpha < 1/255; alpha = min(0.999, o exp(-sigma)); the pixel is done, exclusive, once the
    transmittance would fall to 1e-4 or below), differentiated by autograd, with `means2d.absgrad` filled
    as RasterizeToPixels3DGSBwd.cu does when absgrad=True.
So everything between our `rasterize_gsplat` and those kernels (argument layout, render modes, meta,
channel chunks) is gsplat's real code. `gsplat.spherical_harmonics` (our SH colour under backend gsplat) is replaced
by gsplat's torch reference `_spherical_harmonics`. Not replaced: packed=True, other camera models, masks, and
rasterization's own SH (sh_degree must be None). What only a GPU can check is gsplat's CUDA build and the
arithmetic of its kernels (`-use_fast_math`: __expf, __logf; float32 sums in another order).

Entries of culled Gaussians (radii 0) that the CUDA kernel never writes (`at::empty`) are NaN here, so any
reader of them shows up in a test.
"""

from __future__ import annotations

import math

import gsplat
import gsplat.rendering
import torch
from gsplat.cuda._torch_impl import (
    _fully_fused_projection,
    _isect_offset_encode,
    _isect_tiles,
    _persp_proj,
    _quat_scale_to_covar_preci,
    _spherical_harmonics,
    _world_to_cam,
)
from torch import Tensor

from matspray.render import backend as backend_module

# constants compiled into gsplat 1.5.3's kernels
ALPHA_THRESHOLD = 1.0 / 255.0  # cuda/include/Common.h
MAX_ALPHA = 0.999  # RasterizeToPixels3DGSFwd.cu: min(0.999f, opac * __expf(-sigma))
DONE_TRANSMITTANCE = 1e-4  # RasterizeToPixels3DGSFwd.cu: if (next_T <= 1e-4f) done, this hit excluded
MAX_EXTEND = 3.33  # ProjectionEWA3DGSFused.cu: radius in sigmas before the opacity-aware bound


def gsplat_on_cpu(monkeypatch) -> None:
    """Within the test: gsplat.rasterization runs on the CPU, and
    resolve_backend('gsplat' | 'auto', cpu) gives gsplat."""
    monkeypatch.setattr(gsplat.rendering, "fully_fused_projection", fully_fused_projection)
    monkeypatch.setattr(gsplat.rendering, "isect_tiles", isect_tiles)
    monkeypatch.setattr(gsplat.rendering, "isect_offset_encode", isect_offset_encode)
    monkeypatch.setattr(gsplat.rendering, "rasterize_to_pixels", rasterize_to_pixels)
    monkeypatch.setattr(gsplat, "spherical_harmonics", _spherical_harmonics)
    monkeypatch.setattr(backend_module, "gsplat_device_error", lambda device, notify=None: None)


def fully_fused_projection(
    means,
    covars,
    quats,
    scales,
    viewmats,
    Ks,
    width,
    height,
    eps2d=0.3,
    near_plane=0.01,
    far_plane=1e10,
    radius_clip=0.0,
    packed=False,
    sparse_grad=False,
    calc_compensations=False,
    camera_model="pinhole",
    opacities=None,
):
    """gsplat.fully_fused_projection (packed=False): radii [..., C, N, 2] int32, means2d [..., C, N, 2],
    depths [..., C, N], conics [..., C, N, 3], compensations [..., C, N] or None."""
    if packed or sparse_grad or camera_model != "pinhole":
        raise NotImplementedError("gsplat_cpu: packed=False, pinhole cameras only")
    if covars is None:
        covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)  # [..., N, 3, 3]
    else:  # upper triangle [..., N, 6] -> [..., N, 3, 3]
        covars = covars[..., [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(covars.shape[:-1] + (3, 3))
    _, means2d, depths, conics, compensations = _fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, calc_compensations, camera_model
    )
    radii = kernel_radii(
        means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, radius_clip, opacities, compensations
    )
    # what the kernel never writes for a culled Gaussian is at::empty's memory: NaN here
    drawn = (radii > 0).any(dim=-1)  # [..., C, N]
    means2d, conics = (torch.where(drawn[..., None], t, torch.full_like(t, math.nan)) for t in (means2d, conics))
    depths = torch.where(drawn, depths, torch.full_like(depths, math.nan))
    return radii, means2d, depths, conics, compensations


@torch.no_grad()
def kernel_radii(
    means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, radius_clip, opacities, compensations
) -> Tensor:  # [..., C, N, 2] int32
    """ProjectionEWA3DGSFused.cu's radii, in its order of tests: outside [near, far] -> 0; det of the blurred 2D
    covariance <= 0 -> 0; opacity (times compensation) < 1/255 -> 0; otherwise per axis
    ceil(extend * sqrt(cov2d_ii)) with extend = min(3.33, sqrt(2 ln(opacity * 255))); both <= radius_clip
    -> 0; the box [mean - r, mean + r] not overlapping the image -> 0."""
    means_c, covars_c = _world_to_cam(means, covars, viewmats)
    means2d, cov2d = _persp_proj(means_c, covars_c, Ks, width, height)  # [..., C, N, 2], [..., C, N, 2, 2]
    cov2d = cov2d + eps2d * torch.eye(2, dtype=cov2d.dtype)
    depths = means_c[..., 2]
    det = cov2d[..., 0, 0] * cov2d[..., 1, 1] - cov2d[..., 0, 1] * cov2d[..., 1, 0]
    keep = (depths >= near_plane) & (depths <= far_plane) & (det > 0)
    extend = torch.full_like(depths, MAX_EXTEND)
    if opacities is not None:
        opacity = opacities[..., None, :].expand_as(depths)
        if compensations is not None:
            opacity = opacity * compensations
        keep &= opacity >= ALPHA_THRESHOLD
        extend = torch.minimum(extend, torch.sqrt(2.0 * torch.log((opacity / ALPHA_THRESHOLD).clamp_min(1.0))))
    radius = torch.ceil(
        extend[..., None] * torch.sqrt(torch.diagonal(cov2d, dim1=-2, dim2=-1).clamp_min(0.0))
    )  # [..., C, N, 2]
    keep &= (radius > radius_clip).any(dim=-1)
    size = torch.tensor([width, height], dtype=radius.dtype)
    keep &= ((means2d + radius > 0) & (means2d - radius < size)).all(dim=-1)
    return torch.where(keep[..., None], radius, torch.zeros_like(radius)).int()


def isect_tiles(
    means2d,
    radii,
    depths,
    tile_size,
    tile_width,
    tile_height,
    sort=True,
    segmented=False,
    packed=False,
    n_images=None,
    image_ids=None,
    gaussian_ids=None,
):
    """gsplat.isect_tiles (packed=False): tiles_per_gauss [..., N], isect_ids [M], flatten_ids [M] int32."""
    if packed:
        raise NotImplementedError("gsplat_cpu: packed=False only")
    tiles_per_gauss, isect_ids, flatten_ids = _isect_tiles(
        means2d, radii, depths, tile_size, tile_width, tile_height, sort
    )
    return tiles_per_gauss, isect_ids, flatten_ids.int()


def isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
    """gsplat.isect_offset_encode: the first intersection of each tile [I, tile_height, tile_width] int32."""
    return _isect_offset_encode(isect_ids, n_images, tile_width, tile_height)


def rasterize_to_pixels(
    means2d,
    conics,
    colors,
    opacities,
    image_width,
    image_height,
    tile_size,
    isect_offsets,
    flatten_ids,
    backgrounds=None,
    masks=None,
    packed=False,
    absgrad=False,
):
    """gsplat.rasterize_to_pixels (packed=False, no masks): colours [..., H, W, D], alphas [..., H, W, 1]."""
    if packed or masks is not None:
        raise NotImplementedError("gsplat_cpu: packed=False without masks only")
    image_dims, num = means2d.shape[:-2], means2d.shape[-2]
    images = math.prod(image_dims)
    ids, listed = pixel_hit_lists(
        isect_offsets.reshape(images, -1), flatten_ids.long(), image_width, image_height, tile_size
    )
    hit_means = _HitMeans.apply(means2d, ids, absgrad)  # [I, H * W, K, 2]
    hit_conics = conics.reshape(images * num, 3)[ids]  # [I, H * W, K, 3]
    hit_opacities = opacities.reshape(images * num)[ids]  # [I, H * W, K]
    hit_colors = colors.reshape(images * num, -1)[ids]  # [I, H * W, K, D]
    rows, cols = torch.meshgrid(torch.arange(image_height), torch.arange(image_width), indexing="ij")
    centres = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=-1).to(means2d) + 0.5  # [H * W, 2]
    weights, transmittance = blend_weights(hit_means - centres[:, None, :], hit_conics, hit_opacities, listed)
    render = (weights[..., None] * hit_colors).sum(dim=-2)  # [I, H * W, D]
    if backgrounds is not None:
        render = render + transmittance[..., None] * backgrounds.reshape(images, 1, -1)
    shape = image_dims + (image_height, image_width)
    return render.reshape(shape + (-1,)), (1.0 - transmittance).reshape(shape + (1,))


@torch.no_grad()
def pixel_hit_lists(offsets: Tensor, flatten_ids: Tensor, width: int, height: int, tile_size: int):
    """Each pixel's candidate hits, the intersections of its tile in sorted order: flattened Gaussian ids
    [I, H * W, K] (K the longest tile list) and which of them are real [I, H * W, K] bool.
    offsets [I, tiles]: a tile's list ends where the next one starts, the last one at len(flatten_ids)."""
    starts = offsets.long().reshape(-1)  # [I * tiles]
    ends = torch.cat([starts[1:], torch.tensor([len(flatten_ids)])])
    longest = int((ends - starts).max()) if len(starts) else 0
    slots = starts[:, None] + torch.arange(longest)  # [I * tiles, K]
    listed = slots < ends[:, None]
    ids = flatten_ids[slots.clamp(max=max(len(flatten_ids) - 1, 0))] if len(flatten_ids) else slots * 0
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tiles_x = math.ceil(width / tile_size)
    pixel_tile = ((rows // tile_size) * tiles_x + cols // tile_size).reshape(-1)  # [H * W]
    images, tiles = offsets.shape
    image_tile = (torch.arange(images)[:, None] * tiles + pixel_tile).reshape(-1)  # [I * H * W]
    return ids[image_tile].reshape(images, height * width, longest), listed[image_tile].reshape(
        images, height * width, longest
    )


def blend_weights(delta: Tensor, conics: Tensor, opacities: Tensor, listed: Tensor) -> tuple[Tensor, Tensor]:
    """RasterizeToPixels3DGSFwd.cu's front-to-back loop over each pixel's hits [..., K], vectorised: weights
    alpha_k T_k of the blended hits [..., K] (0 elsewhere) and the final transmittance [...]."""
    a, b, c = conics.unbind(-1)
    dx, dy = delta.unbind(-1)  # mean - pixel centre
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=MAX_ALPHA)
    used = listed & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))  # a skipped hit leaves T as it is (1 - 0 = 1 exactly)
    after = torch.cumprod(1.0 - alpha, dim=-1)  # [..., K] T after each hit, multiplied in order as the kernel does
    before = torch.cat([torch.ones_like(after[..., :1]), after[..., :-1]], dim=-1)
    done = used & (after <= DONE_TRANSMITTANCE)  # this hit would end the pixel: it and all behind it are dropped
    blended = used & (torch.cumsum(done.int(), dim=-1) == 0)
    weights = torch.where(blended, alpha * before, torch.zeros_like(alpha))
    transmittance = torch.where(blended, 1.0 - alpha, torch.ones_like(alpha)).prod(dim=-1)
    return weights, transmittance


class _HitMeans(torch.autograd.Function):
    """means2d gathered per (pixel, hit) [I, H * W, K, 2]. Its backward receives each pixel's own
    d loss / d means2d, which is what RasterizeToPixels3DGSBwd.cu sums as absolute values into
    means2d.absgrad [..., N, 2] when absgrad=True (set on the tensor gsplat passed in, replacing any earlier one)."""

    @staticmethod
    def forward(ctx, means2d, ids, absgrad):
        ctx.save_for_backward(means2d, ids)
        ctx.absgrad = absgrad
        return means2d.reshape(-1, 2)[ids]

    @staticmethod
    def backward(ctx, grad):
        means2d, ids = ctx.saved_tensors
        per_hit = grad.reshape(-1, 2)  # [I * H * W * K, 2]
        flat_ids = ids.reshape(-1)
        grad_means = torch.zeros_like(means2d).reshape(-1, 2).index_add_(0, flat_ids, per_hit)
        if ctx.absgrad:
            means2d.absgrad = (
                torch.zeros_like(means2d).reshape(-1, 2).index_add_(0, flat_ids, per_hit.abs()).reshape(means2d.shape)
            )
        return grad_means.reshape(means2d.shape), None, None
