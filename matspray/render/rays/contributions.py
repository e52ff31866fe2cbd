"""Which Gaussians each camera ray hits, front to back, with the 3DGRT response (paper eq. 1-2).

For a ray o + tau d and a Gaussian (mu, Sigma, opacity alpha) the response peaks at
    tau_max = (mu - o)^T Sigma^-1 d / (d^T Sigma^-1 d),   x_max = o + tau_max d               (1)
    alpha_max = alpha * exp(-lambda / 2 * (x_max - mu)^T Sigma^-1 (x_max - mu))             (2)
Hits are ordered by tau_max and blended front to back: weight_k = alpha_max_k * prod_{j<k}(1 - alpha_max_j),
with the 3DGS conventions (alpha_max clamped to max_alpha, hits under min_alpha skipped, the ray stops
before its transmittance would fall below min_transmittance).

All of it is evaluated in each Gaussian's whitened frame (where it is the unit normal distribution),
in float64, with no gradients. Candidate rays are culled per Gaussian: the rays that can reach
alpha_max >= min_alpha are exactly those through the ellipsoid (x - mu)^T Sigma^-1 (x - mu) <= k^2,
k^2 = 2 ln(alpha / min_alpha) / lambda, whose image is an ellipse found exactly through its dual conic.
Only the sub-pixel samples of pixels meeting that ellipse are evaluated, a band of rows at a time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.compositing import log_transmittance, ray_major_order_by_depth, surviving_hits
from matspray.render.pairs import (
    EMPTY_BOX,
    box_pixel_pairs,
    clip_rows,
    constant,
    ellipse_pixel_pairs,
    pixel_boxes,
    row_bands,
)
from matspray.render.projection import log_opacity_ratio
from matspray.render.rays.cuda import max_response, simulated
from matspray.render.settings import RasterSettings

FUSED = [True]  # on a CUDA device, the rays' response by `cuda_rays`' kernel (False: by torch operations)


@dataclass
class Contributions:
    """Ray-Gaussian hits of one camera, sorted by ray and then front to back along each ray."""

    gaussian_ids: Tensor  # [M] long
    sample_ids: Tensor  # [M] long: index of the ray in `camera.rays(samples_per_side)` order
    #                     (pixel row-major, then the s x s sub-pixel grid row-major)
    weights: Tensor  # [M] alpha_max * transmittance in front of the hit
    alphas: Tensor  # [M] alpha_max of eq. (2), after the max_alpha clamp
    depths: Tensor  # [M] camera-space z of x_max
    samples_per_side: int
    width: int
    height: int

    def __len__(self) -> int:
        return int(self.gaussian_ids.numel())

    @property
    def num_rays(self) -> int:
        return self.width * self.height * self.samples_per_side**2

    @property
    def pixel_ids(self) -> Tensor:  # [M] row-major pixel index of each hit's ray
        return torch.div(self.sample_ids, self.samples_per_side**2, rounding_mode="floor")

    def ray_alpha(self) -> Tensor:  # [num_rays] accumulated opacity of every ray (sum of its weights)
        return self.weights.new_zeros(self.num_rays).index_add_(0, self.sample_ids, self.weights)

    def pixel_alpha(self) -> Tensor:  # [H, W] accumulated opacity averaged over each pixel's samples
        per_ray = self.ray_alpha().reshape(self.height * self.width, self.samples_per_side**2)
        return per_ray.mean(dim=1).reshape(self.height, self.width)

    @staticmethod
    def concatenate(parts: list["Contributions"]) -> "Contributions":
        first = parts[0]
        return Contributions(
            *(
                torch.cat([getattr(p, name) for p in parts])
                for name in ("gaussian_ids", "sample_ids", "weights", "alphas", "depths")
            ),
            samples_per_side=first.samples_per_side,
            width=first.width,
            height=first.height,
        )


def contributions(
    gaussians: Gaussians,
    camera: Camera,
    samples_per_side: int = 1,
    **options,
) -> Contributions:
    """Every ray-Gaussian hit of `camera` with s x s rays per pixel; see `iter_contributions`."""
    return Contributions.concatenate(list(iter_contributions(gaussians, camera, samples_per_side, **options)))


@torch.no_grad()
def iter_contributions(
    gaussians: Gaussians,
    camera: Camera,
    samples_per_side: int = 1,
    *,
    falloff: float = 1.0,
    settings: RasterSettings = RasterSettings(),  # its eps2d is the rasterizer's alone
    max_samples: int = 1 << 21,
) -> Iterator[Contributions]:
    """The hits of `camera`'s rays, one band of pixel rows at a time (top to bottom).

    Each part holds complete rays (all hits of every ray of its rows), with global sample ids, so a
    caller can aggregate per Gaussian without holding all hits of a 16 x 16 supersampled view at once.
    `max_samples` bounds the (Gaussian, ray) candidates evaluated per band (about 100 bytes each).
    """
    s = int(samples_per_side)
    if s < 1:
        raise ValueError(f"contributions: samples_per_side must be >= 1, got {samples_per_side}")
    if falloff <= 0:
        raise ValueError(f"contributions: falloff must be > 0, got {falloff}")
    width, height = camera.width, camera.height
    near, min_alpha = settings.near, settings.min_alpha
    frame, opacities, silhouettes = ray_setup(gaussians, camera, falloff, settings)
    K = camera.K.double().to(opacities.device)
    offsets = (torch.arange(s, dtype=torch.float64, device=opacities.device) + 0.5) / s
    sub_y, sub_x = torch.meshgrid(offsets, offsets, indexing="ij")
    sub_x, sub_y = sub_x.reshape(-1) / K[0, 0], sub_y.reshape(-1) / K[1, 1]  # [s*s] direction offsets

    for row_start, row_end in row_bands(silhouettes.boxes, height, max(1, max_samples // (s * s))):
        owner, pixel_ids = silhouettes.candidate_pixels(row_start, row_end, width)
        alphas, depths = _max_response(frame, opacities, owner, pixel_ids, width, K, sub_x, sub_y, falloff)
        hit = torch.nonzero(((alphas >= min_alpha) & (depths > near)).reshape(-1)).squeeze(1)
        pair, sub = torch.div(hit, s * s, rounding_mode="floor"), hit % (s * s)
        first_sample = row_start * width * s * s
        local_ids = pixel_ids.index_select(0, pair) * (s * s) + sub - first_sample
        gaussian_ids = owner.index_select(0, pair)
        alphas = alphas.reshape(-1).index_select(0, hit).clamp(max=settings.max_alpha)
        depths = depths.reshape(-1).index_select(0, hit)

        order = ray_major_order_by_depth(local_ids, depths.float())
        local_ids, gaussian_ids = local_ids.index_select(0, order), gaussian_ids.index_select(0, order)
        alphas, depths = alphas.index_select(0, order), depths.index_select(0, order)
        num_rays = (row_end - row_start) * width * s * s
        log_keep, log_T = log_transmittance(alphas, local_ids, num_rays)
        alive = torch.nonzero(surviving_hits(log_keep, log_T, settings.min_transmittance)).squeeze(1)
        local_ids, gaussian_ids = local_ids.index_select(0, alive), gaussian_ids.index_select(0, alive)
        alphas, depths = alphas.index_select(0, alive), depths.index_select(0, alive)
        weights = alphas * torch.exp(log_T.index_select(0, alive))
        dtype = gaussians.means.dtype
        yield Contributions(
            gaussian_ids=gaussian_ids,
            sample_ids=local_ids + first_sample,
            weights=weights.to(dtype),
            alphas=alphas.to(dtype),
            depths=depths.to(dtype),
            samples_per_side=s,
            width=width,
            height=height,
        )


def ray_setup(
    gaussians: Gaussians, camera: Camera, falloff: float, settings: RasterSettings
) -> tuple[tuple[Tensor, Tensor], Tensor, "_Silhouettes"]:
    """What tracing `camera`'s rays reads of each Gaussian, float64: its whitened frame (A [N, 3, 3], origin [N, 3]),
    its opacity [N] and the silhouette of the region where a ray reaches min_alpha (boxes empty where none can)."""
    frame = _whitened_frames(gaussians, camera)
    opacities = gaussians.opacities.detach().double()
    radius2 = 2.0 * log_opacity_ratio(opacities, settings.min_alpha) / falloff  # [N] k^2
    silhouettes = _ellipsoid_silhouettes(gaussians, camera, radius2, settings.near)
    faint = (opacities < settings.min_alpha)[:, None]  # no ray reaches min_alpha
    silhouettes.boxes = torch.where(faint, constant(EMPTY_BOX, opacities.device), silhouettes.boxes)
    return frame, opacities, silhouettes


def _whitened_frames(gaussians: Gaussians, camera: Camera) -> tuple[Tensor, Tensor]:
    """Per Gaussian, float64: A [N, 3, 3] mapping camera-space vectors into the whitened frame
    (A = diag(1/s) R_cam^T) and the camera centre in that frame, o = -A mu_cam [N, 3]."""
    g = gaussians.detach().to(dtype=torch.float64)
    view = camera.viewmat.double().to(g.device)
    mean_cam = g.means @ view[:3, :3].T + view[:3, 3]
    axes_cam = view[:3, :3] @ g.rotation_matrices()  # [N, 3, 3]
    A = axes_cam.transpose(1, 2) / g.scales[:, :, None]
    origin = -(A @ mean_cam[:, :, None])[..., 0]
    return A, origin


def _max_response(
    frame: tuple[Tensor, Tensor],  # A [N, 3, 3], origin [N, 3] from _whitened_frames
    opacities: Tensor,  # [N] float64
    owner: Tensor,  # [P] Gaussian of each (Gaussian, pixel) candidate
    pixel_ids: Tensor,  # [P] row-major pixel
    width: int,
    K: Tensor,  # [3, 3] float64
    sub_x: Tensor,  # [S] sub-sample offsets of the direction's x (already divided by fx)
    sub_y: Tensor,  # [S]
    falloff: float,
) -> tuple[Tensor, Tensor]:  # alpha_max [P, S] (unclamped), camera z of x_max [P, S]
    """Eq. (1)-(2) for every sub-pixel ray of every candidate pixel.

    Directions are d = ((x - cx) / fx, (y - cy) / fy, 1) in camera space, so tau_max is the camera z
    of x_max. In the whitened frame the Gaussian is exp(-|x|^2 / 2); with o' = A(o - mu), d' = A d:
    tau_max = -o'.d' / d'.d' and the squared Mahalanobis distance of x_max is |o'|^2 - (o'.d')^2 / d'.d'.
    Across a pixel's samples d' = d0 + u ax + v ay is affine in the sub-pixel offsets (u, v), so o'.d'
    and d'.d' are a linear and a quadratic polynomial in (u, v) whose coefficients are per pixel.
    """
    if FUSED[0] and (owner.is_cuda or simulated()):  # one kernel, not a few dozen passes over the band (`cuda_rays`)
        fused = max_response(frame, opacities, owner, pixel_ids, width, K, sub_x, sub_y, falloff)
        if fused is not None:
            return fused
    A, origin = frame[0].index_select(0, owner), frame[1].index_select(0, owner)  # [P, 3, 3], [P, 3]
    rows = torch.div(pixel_ids, width, rounding_mode="floor")
    corner_x = ((pixel_ids - rows * width).double() - K[0, 2]) / K[0, 0]
    corner_y = (rows.double() - K[1, 2]) / K[1, 1]
    d0 = (
        A[:, :, 0] * corner_x[:, None] + A[:, :, 1] * corner_y[:, None] + A[:, :, 2]
    )  # [P, 3] through the top-left corner
    ax, ay = A[:, :, 0], A[:, :, 1]  # d' per unit of u and of v
    dot = lambda p, q: (p * q).sum(-1)  # noqa: E731
    od = dot(origin, d0)[:, None] + dot(origin, ax)[:, None] * sub_x + dot(origin, ay)[:, None] * sub_y  # [P, S]
    dd = (
        dot(d0, d0)[:, None]
        + (2 * dot(d0, ax))[:, None] * sub_x
        + (2 * dot(d0, ay))[:, None] * sub_y
        + dot(ax, ax)[:, None] * (sub_x * sub_x)
        + (2 * dot(ax, ay))[:, None] * (sub_x * sub_y)
        + dot(ay, ay)[:, None] * (sub_y * sub_y)
    )
    tau = -od / dd
    mahalanobis2 = (dot(origin, origin)[:, None] + od * tau).clamp_min(0.0)
    alphas = opacities.index_select(0, owner)[:, None] * torch.exp(-0.5 * falloff * mahalanobis2)
    return alphas, tau


@dataclass
class _Silhouettes:
    """Images of the ellipsoids (x - mu)^T Sigma^-1 (x - mu) <= k^2: ellipses (x - c)^T E^-1 (x - c) <= 1."""

    boxes: Tensor  # [N, 4] pixels whose area meets the silhouette; empty when nothing can be hit
    centres: Tensor  # [N, 2] c
    conics: Tensor  # [N, 3] (a, b, c) of E^-1
    unbounded: Tensor  # [N] bool: the ellipsoid reaches behind the camera plane; its box is the whole image
    any_unbounded: bool = True  # whether any is (read once per view: the bands skip the whole-image boxes, and their
    # host reads, when none is)

    def candidate_pixels(self, row_start: int, row_end: int, width: int) -> tuple[Tensor, Tensor]:
        """Owner [P] and pixel id [P] of every pixel whose area meets a silhouette within the rows."""
        boxes = clip_rows(self.boxes, row_start, row_end)
        bounded = torch.where(self.unbounded[:, None], constant(EMPTY_BOX, boxes.device), boxes)
        owner, pixel_ids = ellipse_pixel_pairs(
            bounded, self.centres, self.conics, torch.ones_like(self.centres[:, 0]), width, touch="area"
        )
        if not self.any_unbounded:
            return owner, pixel_ids
        whole = torch.where(self.unbounded[:, None], boxes, constant(EMPTY_BOX, boxes.device))
        owner_whole, pixel_ids_whole = box_pixel_pairs(whole, width)
        return torch.cat([owner, owner_whole]), torch.cat([pixel_ids, pixel_ids_whole])


def _ellipsoid_silhouettes(gaussians: Gaussians, camera: Camera, radius2: Tensor, near: float) -> _Silhouettes:
    """With Q* = k^2 Sigma_cam - mu_cam mu_cam^T, the dual conic of the silhouette is C* = K Q* K^T.
    Scaled so that C*_22 = -1 it reads [[E - c c^T, -c], [-c^T, -1]]. An ellipsoid reaching behind the
    camera plane (C*_22 >= 0) has no bounded image and gets the whole image; one entirely behind the
    near plane gets an empty box."""
    g = gaussians.detach().to(dtype=torch.float64)
    view = camera.viewmat.double().to(g.device)
    K = camera.K.double().to(g.device)
    mean_cam = g.means @ view[:3, :3].T + view[:3, 3]  # [N, 3]
    L = view[:3, :3] @ g.scaled_axes()  # [N, 3, 3]
    shape = radius2[:, None, None] * (L @ L.transpose(1, 2))  # k^2 Sigma_cam
    dual = K @ (shape - mean_cam[:, :, None] * mean_cam[:, None, :]) @ K.T  # [N, 3, 3]
    z, z_extent = mean_cam[:, 2], torch.sqrt(shape[:, 2, 2].clamp_min(0.0))
    unbounded = z - z_extent <= 1e-9 * z.abs().clamp_min(1.0)
    scale = torch.where(unbounded, torch.ones_like(z), -1.0 / dual[:, 2, 2])
    dual = dual * scale[:, None, None]
    centres = -dual[:, :2, 2]
    E = dual[:, :2, :2] + centres[:, :, None] * centres[:, None, :]  # [N, 2, 2]
    det = (E[:, 0, 0] * E[:, 1, 1] - E[:, 0, 1] ** 2).clamp_min(1e-30)
    conics = torch.stack([E[:, 1, 1], -E[:, 0, 1], E[:, 0, 0]], dim=-1) / det[:, None]
    half = torch.sqrt(torch.stack([E[:, 0, 0], E[:, 1, 1]], dim=-1).clamp_min(0.0))
    boxes = pixel_boxes(centres - half, centres + half, camera.width, camera.height, centres=False)
    full = constant((0, 0, camera.width - 1, camera.height - 1), boxes.device)
    boxes = torch.where(unbounded[:, None], full, boxes)
    behind = z + z_extent <= near
    boxes = torch.where(behind[:, None], constant(EMPTY_BOX, boxes.device), boxes)
    unbounded = unbounded & ~behind
    return _Silhouettes(boxes, centres, conics, unbounded, bool(unbounded.any()))
