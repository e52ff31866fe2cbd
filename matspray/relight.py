"""Render a relightable asset under any environment light: G-buffer rasterization + split-sum shading."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians


@dataclass
class Asset:
    """What refinement produces: Gaussians with PBR materials and shading normals."""

    gaussians: Gaussians
    materials: Tensor  # [N, 5] base color rgb (linear), roughness, metallic
    normals: Tensor  # [N, 3] unit; sign is fixed per view when rendering

    def __post_init__(self):
        n = len(self.gaussians)
        if self.materials.shape != (n, 5) or self.normals.shape != (n, 3):
            raise ValueError(f"asset: materials must be [{n}, 5] and normals [{n}, 3], got {tuple(self.materials.shape)}, {tuple(self.normals.shape)}")


def orient_normals(normals: Tensor, means: Tensor, camera: Camera) -> Tensor:  # [N, 3], [N, 3] -> [N, 3]
    """Flip each normal to face the camera (Gaussian normals have no reliable sign)."""
    to_camera = camera.center.to(means) - means
    facing = (normals * to_camera).sum(-1, keepdim=True) >= 0
    return torch.where(facing, normals, -normals)


def render_gbuffer(asset: Asset, camera: Camera):
    """Rasterize materials and normals for `camera` -> GBuffer (materials divided by coverage)."""
    from matspray.render.deferred import GBuffer
    from matspray.render.rasterize import rasterize

    normals = orient_normals(asset.normals, asset.gaussians.means, camera)
    out = rasterize(asset.gaussians, camera, torch.cat([asset.materials, normals], dim=-1))
    f = out.features
    return GBuffer.from_accumulated(f[..., :3], f[..., 3], f[..., 4], f[..., 5:8], out.alpha)


def render_relit(asset: Asset, camera: Camera, light, background: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Linear RGB [H, W, 3] of the asset lit by `light` (EnvironmentMap or PrefilteredEnvironment),
    composited over `background` ([3] linear; None = black), and the coverage alpha [H, W]."""
    from matspray.render.deferred import shade_gbuffer

    with torch.no_grad():
        gbuffer = render_gbuffer(asset, camera)
        return shade_gbuffer(gbuffer, camera, light, background), gbuffer.alpha


def orbit_cameras(reference: list[Camera], target: Tensor, frames: int = 60, up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """Cameras circling `target` [3] about the world up axis, at the mean distance and elevation of the
    reference cameras and with their intrinsics and image size."""
    target = torch.as_tensor(target, dtype=torch.float64)
    up_axis = F.normalize(torch.tensor(up, dtype=torch.float64), dim=0)
    offsets = torch.stack([c.center.double() - target for c in reference])
    distance = float(offsets.norm(dim=-1).mean())
    elevation = float(torch.asin((F.normalize(offsets, dim=-1) @ up_axis).clamp(-0.99, 0.99)).mean())
    first = reference[0]
    cameras = []
    for i in range(frames):
        azimuth = 2 * math.pi * i / frames
        direction = torch.tensor([math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation), math.sin(elevation)], dtype=torch.float64)
        camera = Camera.look_at(target + distance * direction, target, up_axis, first.fov_x, first.width, first.height)
        camera.K = first.K.clone()
        cameras.append(camera)
    return cameras
