"""Projection of 3D Gaussians onto the image plane (EWA splatting, as in 3DGS).

A Gaussian with world mean mu and covariance Sigma = L L^T (L = R diag(s), its scaled axes) becomes, in
pixel coordinates, a 2D Gaussian with mean pi(mu) and covariance  (J W L)(J W L)^T + eps2d * I,  where
W is the world-to-camera rotation,
J the Jacobian of the perspective projection at the camera-space mean, and eps2d (0.3 px^2 in 3DGS)
a low-pass filter that keeps every footprint at least about a pixel wide.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# 3DGS evaluates the projection Jacobian with the camera-space direction clamped to 1.3 times the
# image half-extent, so Gaussians far outside the view do not get enormous footprints.
JACOBIAN_FOV_MARGIN = 1.3


@dataclass
class ProjectedGaussians:
    means2d: Tensor  # [N, 2] pixel coordinates (x, y) of the projected centres
    cov2d: Tensor  # [N, 3] (xx, xy, yy) of the 2D covariance, low-pass filter included
    conics: Tensor  # [N, 3] (a, b, c) of the inverse covariance [[a, b], [b, c]]
    depths: Tensor  # [N] camera-space z of the centres
    valid: Tensor  # [N] bool: in front of the near plane with a non-degenerate footprint


def project_gaussians(
    means: Tensor,  # [N, 3] world space
    scaled_axes: Tensor,  # [N, 3, 3] L = R diag(scales), the covariance is L L^T (world space)
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float = 0.01,
    eps2d: float = 0.3,
) -> ProjectedGaussians:
    """EWA projection of every Gaussian; differentiable w.r.t. means and scaled axes.

    Gaussians behind the near plane or with a singular footprint are marked invalid; their outputs
    hold finite placeholder values so that gradients stay finite.
    """
    R, t = viewmat[:3, :3].to(means), viewmat[:3, 3].to(means)
    K = K.to(means)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cam = means @ R.T + t  # [N, 3]
    z = cam[:, 2]
    valid = z > near
    z = torch.where(valid, z, torch.ones_like(z))
    x, y = cam[:, 0] / z, cam[:, 1] / z  # [N] normalised image coordinates
    means2d = torch.stack([fx * x + cx, fy * y + cy], dim=-1)

    lim_x_lo, lim_x_hi = JACOBIAN_FOV_MARGIN * cx / fx, JACOBIAN_FOV_MARGIN * (width - cx) / fx
    lim_y_lo, lim_y_hi = JACOBIAN_FOV_MARGIN * cy / fy, JACOBIAN_FOV_MARGIN * (height - cy) / fy
    xc = torch.maximum(torch.minimum(x, lim_x_hi), -lim_x_lo)
    yc = torch.maximum(torch.minimum(y, lim_y_hi), -lim_y_lo)
    # T = J W L, with J = [[fx / z, 0, -fx xc / z], [0, fy / z, -fy yc / z]], written out per row
    # (elementwise ops on [N, 3] beat a batched 3x3 matmul on the CPU)
    WL = torch.einsum("ij,njk->nik", R, scaled_axes)  # [N, 3, 3]
    row_x = (fx / z)[:, None] * (WL[:, 0] - xc[:, None] * WL[:, 2])  # [N, 3]
    row_y = (fy / z)[:, None] * (WL[:, 1] - yc[:, None] * WL[:, 2])
    cov_xx = (row_x * row_x).sum(-1) + eps2d
    cov_xy = (row_x * row_y).sum(-1)
    cov_yy = (row_y * row_y).sum(-1) + eps2d
    det = cov_xx * cov_yy - cov_xy * cov_xy
    valid = valid & (det > 1e-12 * (cov_xx * cov_yy).abs().clamp_min(1e-30))
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cov_yy / det, -cov_xy / det, cov_xx / det], dim=-1)
    return ProjectedGaussians(
        means2d=means2d,
        cov2d=torch.stack([cov_xx, cov_xy, cov_yy], dim=-1),
        conics=conics,
        depths=cam[:, 2],
        valid=valid,
    )


def footprint_eigenvalues(cov2d: Tensor) -> tuple[Tensor, Tensor]:  # [N, 3] (a, b, c) -> [N], [N] px^2
    """The variances along a footprint's major and minor axes (the 2 x 2 covariance's eigenvalues, clamped >= 0)."""
    mid = 0.5 * (cov2d[:, 0] + cov2d[:, 2])
    spread = torch.sqrt((mid * mid - (cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2)).clamp_min(0.0))
    return (mid + spread).clamp_min(0.0), (mid - spread).clamp_min(0.0)


def max_eigen_radius(cov2d: Tensor) -> Tensor:  # [N, 3] -> [N] 3-sigma radius of the major axis (px)
    return 3.0 * torch.sqrt(footprint_eigenvalues(cov2d)[0])


def log_opacity_ratio(opacities: Tensor, min_alpha: float) -> Tensor:  # [N] -> [N] ln(opacity / min_alpha), >= 0
    return torch.log((opacities / min_alpha).clamp_min(1.0))
