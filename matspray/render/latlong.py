"""Lat-long (equirectangular) environment-map convention, shared by every module.

World up is +z (Blender / NeRF-synthetic). An environment map is [H, 2H, 3] linear RGB; row 0 is
straight up. A direction d = (x, y, z) maps to
    u = atan2(y, -x) / (2 pi) + 0.5        (column, in [0, 1), left to right)
    v = acos(z) / pi                       (row, in [0, 1], top to bottom)
which is Blender's world equirectangular mapping, so maps made for Blender light our scenes the same.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


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
