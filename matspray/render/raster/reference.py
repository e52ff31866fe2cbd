"""Readable references for the fast renderers: the same results, computed the slow and obvious way.

`trace_rays` is the ray tracer of the paper's material lifting (Sec. 2D-to-3D Material Lifting, after
3DGRT): every ray of a camera against every Gaussian. For a ray o + tau d and a Gaussian with mean mu,
covariance Sigma and opacity alpha, the response is largest at

    tau_max = (mu - o)^T Sigma^-1 d / (d^T Sigma^-1 d),   x_max = o + tau_max d                  (1)

where the Gaussian contributes the opacity, for a falloff lambda > 0,

    alpha_max = alpha * exp(-lambda / 2 * (x_max - mu)^T Sigma^-1 (x_max - mu)).                 (2)

`splat_pixels` is 3DGS's rasterizer: every Gaussian projected to a 2D footprint (EWA splatting), then
every pixel centre against every footprint.

Both blend the hits of a ray (or pixel) front to back with `composite_front_to_back`, under 3DGS's
rules (`RasterSettings`): hits with alpha < min_alpha are skipped, alphas are clamped to max_alpha, and
the ray stops before its transmittance would fall below min_transmittance. The weight of the k-th hit
is alpha_k * prod_{j<k} (1 - alpha_j).

Everything is float64, without gradients, written to be checked line by line against the equations:
the tests compare `matspray.render.rays.contributions` and `matspray.render.raster.rasterize` with these. They
cost O(rays x Gaussians) time and memory; use them on small scenes only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.projection import JACOBIAN_FOV_MARGIN
from matspray.render.settings import RasterSettings


class Hit(NamedTuple):
    """One Gaussian blended into one ray."""

    gaussian: int  # index into the Gaussians
    alpha: float  # alpha_max of eq. (2), clamped to max_alpha
    weight: float  # alpha * transmittance in front of the hit
    depth: float  # camera-space z of x_max


def composite_front_to_back(
    alphas: list[float],  # [K] opacities of the candidate hits of one ray, front to back
    settings: RasterSettings = RasterSettings(),
) -> list[tuple[int, float, float]]:  # (k, clamped alpha_k, weight_k) of each blended hit, in order
    """Front-to-back alpha compositing of one ray, as 3DGS does it."""
    transmittance, blended = 1.0, []
    for k, alpha in enumerate(alphas):
        if alpha < settings.min_alpha:
            continue  # too faint to matter
        alpha = min(alpha, settings.max_alpha)
        if transmittance * (1.0 - alpha) < settings.min_transmittance:
            break  # the ray is (nearly) opaque: this hit and all behind it are dropped
        blended.append((k, alpha, alpha * transmittance))
        transmittance *= 1.0 - alpha
    return blended


def max_response(
    origins: Tensor,  # [R, 3] ray origins o
    directions: Tensor,  # [R, 3] ray directions d (any length)
    means: Tensor,  # [N, 3] mu
    inv_covariances: Tensor,  # [N, 3, 3] Sigma^-1
    opacities: Tensor,  # [N] alpha
    falloff: float = 1.0,  # lambda
) -> tuple[Tensor, Tensor, Tensor]:  # tau_max [R, N], x_max [R, N, 3], alpha_max [R, N]
    """Eq. (1)-(2) for every (ray, Gaussian) pair."""
    to_mean = means[None, :, :] - origins[:, None, :]  # [R, N, 3] mu - o
    Sd = torch.einsum("nij,rj->rni", inv_covariances, directions)  # [R, N, 3] Sigma^-1 d
    tau = (to_mean * Sd).sum(-1) / (directions[:, None, :] * Sd).sum(-1)  # [R, N]  eq. (1)
    x_max = origins[:, None, :] + tau[..., None] * directions[:, None, :]  # [R, N, 3]
    offset = x_max - means[None]  # [R, N, 3] x_max - mu
    mahalanobis2 = torch.einsum("rni,nij,rnj->rn", offset, inv_covariances, offset)  # [R, N]
    alpha_max = opacities[None, :] * torch.exp(-0.5 * falloff * mahalanobis2)  # [R, N]  eq. (2)
    return tau, x_max, alpha_max


@torch.no_grad()
def trace_rays(
    gaussians: Gaussians,
    camera: Camera,
    samples_per_side: int = 1,
    *,
    falloff: float = 1.0,
    settings: RasterSettings = RasterSettings(),  # its eps2d is the rasterizer's alone
) -> list[list[Hit]]:  # [H * W * s * s] the blended hits of each ray, front to back
    """Every ray of `camera.rays(samples_per_side)` against every Gaussian (eq. 1-2), composited front
    to back along tau_max. A hit counts only where x_max lies in front of the near plane (camera z)."""
    g = gaussians.detach().to(dtype=torch.float64)
    inv_covariances = torch.linalg.inv(g.covariances())  # [N, 3, 3]
    origins, directions = (t.double() for t in camera.rays(samples_per_side))  # [R, 3] each
    tau, x_max, alpha_max = max_response(origins, directions, g.means, inv_covariances, g.opacities, falloff)
    view = camera.viewmat.double()
    depth = x_max @ view[2, :3] + view[2, 3]  # [R, N] camera z of x_max
    tau, alpha_max, depth = tau.tolist(), alpha_max.tolist(), depth.tolist()  # plain floats for the loops

    hits = []
    for ray in range(len(origins)):
        in_front = [i for i in range(len(g)) if depth[ray][i] > settings.near]
        in_front.sort(key=lambda i: (tau[ray][i], i))  # front to back along the ray
        blended = composite_front_to_back([alpha_max[ray][i] for i in in_front], settings)
        hits.append([Hit(in_front[k], alpha, weight, depth[ray][in_front[k]]) for k, alpha, weight in blended])
    return hits


class Splat(NamedTuple):
    """A Gaussian's footprint on the image (EWA splatting)."""

    depth: float  # camera-space z of the centre: the blending order
    centre: Tensor  # [2] pixel coordinates of the projected mean
    inv_cov2d: Tensor  # [2, 2] inverse of the 2D covariance (the conic)
    opacity: float
    gaussian: int


def project_splats(gaussians: Gaussians, camera: Camera, eps2d: float = 0.3, near: float = 0.01) -> list[Splat]:
    """Each Gaussian in front of the near plane as a 2D Gaussian: mean pi(mu), covariance
    J W Sigma W^T J^T + eps2d I, with W the world-to-camera rotation and J the Jacobian of the
    perspective projection at the camera-space mean t (its x/z, y/z clamped to JACOBIAN_FOV_MARGIN
    times the image half-extent, as 3DGS does)."""
    g = gaussians.detach().to(dtype=torch.float64)
    covariances = g.covariances()  # [N, 3, 3]
    W, translation = camera.viewmat.double()[:3, :3], camera.viewmat.double()[:3, 3]
    K = camera.K.double()
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    splats = []
    for i in range(len(g)):
        t = W @ g.means[i] + translation  # [3] camera-space mean
        z = float(t[2])
        if z <= near:
            continue
        x, y = float(t[0]) / z, float(t[1]) / z
        xc = min(max(x, -JACOBIAN_FOV_MARGIN * cx / fx), JACOBIAN_FOV_MARGIN * (camera.width - cx) / fx)
        yc = min(max(y, -JACOBIAN_FOV_MARGIN * cy / fy), JACOBIAN_FOV_MARGIN * (camera.height - cy) / fy)
        J = torch.tensor([[fx / z, 0.0, -fx * xc / z], [0.0, fy / z, -fy * yc / z]], dtype=torch.float64)  # [2, 3]
        cov2d = J @ W @ covariances[i] @ W.T @ J.T + eps2d * torch.eye(2, dtype=torch.float64)  # [2, 2]
        centre = torch.tensor([fx * x + cx, fy * y + cy], dtype=torch.float64)
        splats.append(Splat(z, centre, torch.linalg.inv(cov2d), float(g.opacities[i]), i))
    return splats


@torch.no_grad()
def splat_pixels(
    gaussians: Gaussians,
    camera: Camera,
    features: Tensor,  # [N, C]
    background: Tensor | None = None,  # [C]; None means zeros
    *,
    settings: RasterSettings = RasterSettings(),
) -> tuple[Tensor, Tensor, Tensor]:  # features [H, W, C], alpha [H, W], depth [H, W] (sum_k w_k z_k)
    """3DGS's forward pass per pixel: the footprints sorted by centre depth, each evaluated at the
    pixel centre, alpha_k = opacity_k exp(-delta^T conic_k delta / 2), composited front to back;
    features[p] = sum_k w_k f_k + (1 - alpha[p]) background."""
    splats = sorted(project_splats(gaussians, camera, settings.eps2d, settings.near), key=lambda s: s.depth)
    num_channels = features.shape[1]
    feats = features.detach().double().tolist()  # [N][C]
    background = [0.0] * num_channels if background is None else background.double().tolist()  # [C]
    H, W = camera.height, camera.width
    rows, cols = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    centres = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=-1) + 0.5  # [H * W, 2] pixel centres
    raw_alpha = torch.zeros(
        H * W, len(splats), dtype=torch.float64
    )  # [H * W, K] opacity_k exp(-delta^T conic_k delta / 2)
    for k, s in enumerate(splats):
        delta = centres - s.centre  # [H * W, 2]
        raw_alpha[:, k] = s.opacity * torch.exp(-0.5 * ((delta @ s.inv_cov2d) * delta).sum(-1))
    raw_alpha = raw_alpha.tolist()

    image, alpha, depth = [], [], []  # per pixel, row-major
    for p in range(H * W):
        colour, coverage, z = [0.0] * num_channels, 0.0, 0.0
        for k, _, weight in composite_front_to_back(raw_alpha[p], settings):
            f = feats[splats[k].gaussian]
            colour = [c + weight * f[j] for j, c in enumerate(colour)]
            coverage += weight
            z += weight * splats[k].depth
        image.append([c + (1.0 - coverage) * b for c, b in zip(colour, background)])
        alpha.append(coverage)
        depth.append(z)
    as_tensor = lambda values, *shape: torch.tensor(values, dtype=torch.float64).reshape(*shape)  # noqa: E731
    return as_tensor(image, H, W, num_channels), as_tensor(alpha, H, W), as_tensor(depth, H, W)
