"""Multi-view inconsistency of per-view maps: how much the values that different views give the
same surface point disagree, measured with true geometry (per-view depth maps).

For every object pixel of a view, its surface point (from the depth map and camera) is projected into
every view; where it lands in front of that view's own depth (within a relative tolerance) it is
visible there, and that view's map value at the pixel is collected. The spread of a point is the
standard deviation of its collected values (points seen by fewer than two views are skipped); the
result is the mean spread over points, per channel. True maps give about 0 (texture edges and
nearest-pixel sampling leave a small floor).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from matspray.data.camera import Camera


@dataclass
class Spread:
    per_channel: Tensor  # [C] mean over points of the per-point standard deviation
    points: int  # surface points seen by at least two views
    mean_views: float  # views that see a point, on average


def backproject(camera: Camera, depth: Tensor, stride: int = 1) -> Tensor:
    """depth [H, W] (camera z, 0 = background) -> world points [P, 3] of the pixel centres with depth > 0,
    taking every `stride`-th such pixel."""
    rows, cols = torch.nonzero(depth > 0, as_tuple=True)
    rows, cols = rows[::stride], cols[::stride]
    z = depth[rows, cols].double()
    K = camera.K.double()
    x = (cols.double() + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows.double() + 0.5 - K[1, 2]) / K[1, 1] * z
    points_cam = torch.stack([x, y, z], dim=-1)  # [P, 3]
    c2w = camera.camtoworld.double()
    return points_cam @ c2w[:3, :3].T + c2w[:3, 3]


def lookup_visible(camera: Camera, depth: Tensor, points: Tensor, tolerance: float) -> tuple[Tensor, Tensor, Tensor]:
    """Where world points [P, 3] land in a view: rows [P], cols [P] (nearest pixel) and visible [P] bool
    (inside the image, in front of the camera, and within `tolerance` * z of the view's depth)."""
    pixels, z = camera.project(points.double())
    cols, rows = pixels[:, 0].floor().long(), pixels[:, 1].floor().long()
    inside = (z > 0) & (cols >= 0) & (rows >= 0) & (cols < camera.width) & (rows < camera.height)
    cols, rows = cols.clamp(0, camera.width - 1), rows.clamp(0, camera.height - 1)
    surface = depth[rows, cols].double()
    visible = inside & (surface > 0) & ((surface - z).abs() <= tolerance * z)
    return rows, cols, visible


def multiview_spread(
    cameras: list[Camera],
    depths: list[Tensor],  # [H, W] per view
    maps: list[Tensor],  # [H, W, C] per view
    tolerance: float = 0.02,
    points_per_view: int = 4000,
) -> Spread:
    total = torch.zeros(maps[0].shape[-1], dtype=torch.float64)
    points, seen = 0, 0.0
    for source in range(len(cameras)):
        count = int((depths[source] > 0).sum())
        if count == 0:
            continue
        world = backproject(cameras[source], depths[source], stride=max(1, count // points_per_view))  # [P, 3]
        values = torch.zeros(len(cameras), world.shape[0], maps[0].shape[-1], dtype=torch.float64)  # [V, P, C]
        valid = torch.zeros(len(cameras), world.shape[0], dtype=torch.bool)  # [V, P]
        for target, (camera, depth, values_map) in enumerate(zip(cameras, depths, maps)):
            rows, cols, visible = lookup_visible(camera, depth, world, tolerance)
            values[target] = values_map[rows, cols].double()
            valid[target] = visible
        n = valid.sum(0)  # [P]
        keep = n >= 2
        if not keep.any():
            continue
        weights = valid[:, keep, None].double()  # [V, P', 1]
        v = values[:, keep]
        mean = (v * weights).sum(0) / n[keep, None]
        std = (((v - mean) ** 2 * weights).sum(0) / n[keep, None]).sqrt()  # [P', C]
        total += std.sum(0)
        points += int(keep.sum())
        seen += float(n[keep].sum())
    if points == 0:
        return Spread(torch.full_like(total, float("nan")).float(), 0, 0.0)
    return Spread((total / points).float(), points, seen / points)
