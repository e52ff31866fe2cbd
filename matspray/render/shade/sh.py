"""Real spherical harmonics colour, degree 0-3, in the convention of 3DGS (so that f_dc / f_rest in
3DGS PLY files mean the same here): rgb = max(0, sum_k c_k Y_k(d) + 0.5), d = unit direction from the
camera centre to the Gaussian."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.render.backend import active_backend, compiled_on_cpu
from matspray.render.sh_constants import MAX_DEGREE, SH_C0, SH_C1, SH_C2, SH_C3, num_sh_bases


def sh_basis(dirs: Tensor, degree: int) -> Tensor:  # [..., 3] unit -> [..., (degree + 1)^2]
    """The real SH basis functions Y_k(d), with 3DGS's signs and ordering (k = l^2 + l + m)."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"sh_basis: degree must be 0..{MAX_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def sh_to_rgb(
    sh: Tensor,  # [N, K, 3] coefficients, K = (degree + 1)^2 (extra bases beyond `degree` are ignored)
    dirs: Tensor,  # [N, 3] unit viewing directions
    degree: int | None = None,  # default: the highest degree K holds
) -> Tensor:  # [N, 3] colour, >= 0
    degree = checked_degree(sh, degree)
    basis = sh_basis(dirs, degree)  # [N, K']
    rgb = (basis[:, :, None] * sh[:, : basis.shape[1]]).sum(dim=1)
    return torch.clamp_min(rgb + 0.5, 0.0)


def checked_degree(sh: Tensor, degree: int | None) -> int:  # sh [N, K, 3]
    """`degree`, or the highest one `sh` holds when None; refused when `sh` has too few coefficients for it."""
    if degree is None:
        degree = int(round(sh.shape[1] ** 0.5)) - 1
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"sh_to_rgb: degree must be 0..{MAX_DEGREE}, got {degree}")
    if num_sh_bases(degree) > sh.shape[1]:
        raise ValueError(f"sh_to_rgb: degree {degree} needs {num_sh_bases(degree)} coefficients, got {sh.shape[1]}")
    return degree


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:  # [..., 3] -> [..., 3] DC coefficient that gives this colour
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: Tensor) -> Tensor:  # [..., 3] -> [..., 3] view-independent colour of a DC coefficient
    return dc * SH_C0 + 0.5


def view_directions(means: Tensor, camera: Camera) -> Tensor:  # [N, 3] -> [N, 3] unit camera-to-Gaussian
    return F.normalize(means - camera.center.to(means), dim=-1)


def sh_colors(gaussians, camera: Camera, degree: int | None = None) -> Tensor:  # -> [N, 3]
    """Colour of every Gaussian as seen from `camera` (differentiable w.r.t. means and sh). Within a block that renders
    with numba, on the CPU, by its compiled loops (matspray.render.numba.sh), which training calls every step."""
    if compiled_on_cpu(gaussians.means.device):
        from matspray.render.numba.sh import CompiledSH  # numba loads where it renders

        return CompiledSH.apply(gaussians.sh, gaussians.means, camera.center, checked_degree(gaussians.sh, degree))
    if active_backend() == "gsplat":  # one fused kernel each way instead of a hundred small operations
        from matspray.render.raster.gsplat import sh_colors_gsplat  # gsplat loads where it renders

        return sh_colors_gsplat(gaussians.sh, gaussians.means, camera.center, checked_degree(gaussians.sh, degree))
    return sh_to_rgb(gaussians.sh, view_directions(gaussians.means, camera), degree)
