"""Lat-long (equirectangular) environment-map convention, shared by every module.

World up is +z (Blender / NeRF-synthetic). An environment map is [H, 2H, 3] linear RGB; row 0 is
straight up. A direction d = (x, y, z) maps to
    u = atan2(y, -x) / (2 pi) + 0.5        (column, in [0, 1), left to right)
    v = acos(z) / pi                       (row, in [0, 1], top to bottom)
(Mitsuba's and ours agree: tests/test_synth_mitsuba.py). Blender's world mapping is this one turned half a turn about
+z: a map made here lights a Blender scene from the opposite side unless its vector is turned by 180 degrees
(`python -m benchmarks.blender_light` renders it; tests/test_blender_light.py).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from matspray.render.shade.sh import sh_basis


def direction_to_uv(d: Tensor) -> Tensor:  # [..., 3] unit -> [..., 2] (u, v) in [0, 1]
    x, y, z = d.unbind(-1)
    u = torch.atan2(y, -x) / (2 * math.pi) + 0.5
    v = torch.acos(z.clamp(-1.0, 1.0)) / math.pi
    return torch.stack([u, v], dim=-1)


def uv_to_direction(uv: Tensor) -> Tensor:  # [..., 2] -> [..., 3] unit
    phi = (uv[..., 0] - 0.5) * 2 * math.pi  # atan2(y, -x)
    theta = uv[..., 1] * math.pi
    sin_t = torch.sin(theta)
    return torch.stack([-sin_t * torch.cos(phi), sin_t * torch.sin(phi), torch.cos(theta)], dim=-1)


def pixel_directions(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """Directions [H, W, 3] through the centres of an H x W lat-long map's pixels."""
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return uv_to_direction(torch.stack([uu, vv], dim=-1))


def pixel_solid_angles(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """Solid angle [H, W] of each pixel of an H x W lat-long map (sums to 4 pi)."""
    edges = torch.arange(height + 1, device=device, dtype=torch.float64) / height * math.pi
    band = (torch.cos(edges[:-1]) - torch.cos(edges[1:])) * (2 * math.pi / width)  # [H]
    return band.to(dtype)[:, None].expand(height, width)


def total_variation(values: Tensor) -> Tensor:  # [H, 2H, C] -> [] mean gradient magnitude per steradian
    """Anisotropic total variation of a lat-long field on the sphere, (1 / 4 pi) * integral of
    |d f / d theta| + |d f / (sin theta d phi)| over the sphere, summed over channels. Per pixel pair:
    a step between rows i and i+1 weighs sin(theta of their edge) * dphi, a step between neighbouring
    columns (wrapping round) weighs dtheta, so the value does not grow at the poles, where pixels shrink.
    Applied to log radiance it measures how noisy a light is, independent of its brightness."""
    height, width = values.shape[:2]
    vertical = (values[1:] - values[:-1]).abs() * _row_edge_weights(height, width, values.dtype, values.device)
    horizontal = (values.roll(-1, dims=1) - values).abs() * (math.pi / height)  # d_theta
    return (vertical.sum() + horizontal.sum()) / (4 * math.pi)


_EDGE_WEIGHTS: dict[tuple, Tensor] = {}


def _row_edge_weights(height: int, width: int, dtype, device) -> Tensor:  # -> [H - 1, 1, 1]
    """sin(theta) d_phi of each boundary between two rows (`total_variation`; made once per size: the refinement
    asks every step)."""
    key = (height, width, dtype, str(device))
    if key not in _EDGE_WEIGHTS:
        edges = torch.arange(1, height, device=device, dtype=dtype) * (math.pi / height)  # [H - 1] row boundaries
        _EDGE_WEIGHTS[key] = (torch.sin(edges) * (2 * math.pi / width))[:, None, None]
    return _EDGE_WEIGHTS[key]


def sh_irradiance_coefficients(map: Tensor) -> Tensor:  # [H, 2H, 3] linear radiance -> [9, 3]
    """Projection of a lat-long map onto the 9 real spherical harmonics of order <= 2: what irradiance,
    the cosine convolution, keeps of a light (Ramamoorthi and Hanrahan 2001)."""
    height, width = map.shape[:2]
    basis = sh_basis(pixel_directions(height, width, map.device, map.dtype), 2)  # [H, W, 9]
    weights = pixel_solid_angles(height, width, map.device, map.dtype)[..., None, None]  # [H, W, 1, 1]
    return (basis[..., :, None] * map[..., None, :] * weights).sum(dim=(0, 1))


COSINE_LOBE_BANDS = (math.pi, 2 * math.pi / 3, math.pi / 4)  # the clamped cosine's SH coefficient per band l = 0, 1, 2


def irradiance_correlation(a: Tensor, b: Tensor) -> float:  # [H, 2H, 3], [h, 2h, 3] -> Pearson r
    """Correlation of two lights' irradiance: Pearson's r of their order-2 spherical-harmonic irradiance
    over a 16 x 32 grid of normals (channels together); 1 means the same diffuse shading up to a scale."""
    normals = pixel_directions(16, 32, dtype=torch.float64).reshape(-1, 3)
    band_scale = torch.tensor(
        [COSINE_LOBE_BANDS[0]] + [COSINE_LOBE_BANDS[1]] * 3 + [COSINE_LOBE_BANDS[2]] * 5, dtype=torch.float64
    )
    basis = sh_basis(normals, 2) * band_scale  # [P, 9]
    fa, fb = ((basis @ sh_irradiance_coefficients(light.double().cpu())).flatten() for light in (a, b))  # [P * 3] each
    fa, fb = fa - fa.mean(), fb - fb.mean()
    return float((fa * fb).sum() / (fa.norm() * fb.norm()).clamp_min(1e-30))
