"""A small analytic test object for geometry tests and benchmarks: a signed-distance shape (a sphere
fused with a rounded box) with a procedural texture and baked diffuse lighting, sphere-traced in
torch, with exact masks and world-space normals. Written in the Blender layout plus
`{split}/{name}_normal.exr`, the layout of `matspray synth`."""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.formats.blender import write_blender
from matspray.data.images import write_raw
from matspray.data.scene import View

LIGHT = F.normalize(torch.tensor([0.4, -0.5, 0.8]), dim=0)
BOUND = 1.0  # the object lies inside [-BOUND, BOUND]^3


def signed_distance(p: Tensor) -> Tensor:  # [P, 3] -> [P]
    sphere = (p - torch.tensor([0.0, 0.0, 0.15])).norm(dim=-1) - 0.5
    q = (p - torch.tensor([0.0, 0.0, -0.35])).abs() - torch.tensor([0.55, 0.35, 0.12])
    box = q.clamp_min(0).norm(dim=-1) + q.max(dim=-1).values.clamp_max(0) - 0.08
    k = 0.1  # smooth union
    h = (0.5 + 0.5 * (box - sphere) / k).clamp(0, 1)
    return box * (1 - h) + sphere * h - k * h * (1 - h)


def surface_normal(p: Tensor, eps: float = 1e-4) -> Tensor:  # [P, 3] -> [P, 3] unit (central differences)
    offsets = torch.eye(3) * eps
    grad = torch.stack([signed_distance(p + o) - signed_distance(p - o) for o in offsets], dim=-1)
    return F.normalize(grad, dim=-1)


def albedo(p: Tensor) -> Tensor:  # [P, 3] -> [P, 3] linear
    stripes = 0.5 + 0.5 * torch.sin(9.0 * p[:, 2] + 3.0 * torch.atan2(p[:, 1], p[:, 0]))
    base = torch.stack([0.75 - 0.3 * stripes, 0.35 + 0.3 * stripes, 0.25 + 0.2 * (p[:, 0] + 0.6).clamp(0, 1)], dim=-1)
    lower = (p[:, 2] < -0.2).float()[:, None]
    return base * (1 - lower) + torch.tensor([0.2, 0.3, 0.7]) * lower


def trace(origins: Tensor, dirs: Tensor, steps: int = 96) -> tuple[Tensor, Tensor]:
    """Sphere tracing from the bounding sphere: hit points [P, 3] and hit mask [P]."""
    b = (origins * dirs).sum(-1)
    c = origins.square().sum(-1) - 3 * BOUND**2
    t = (-b - torch.sqrt((b * b - c).clamp_min(0))).clamp_min(0)
    for _ in range(steps):
        d = signed_distance(origins + t[:, None] * dirs)
        t = (t + d).clamp_max(20.0)
    points = origins + t[:, None] * dirs
    return points, signed_distance(points).abs() < 1e-3


def render_analytic(camera: Camera, supersample: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """Linear colour [H, W, 3], alpha [H, W] and world normals [H, W, 3] (0 off the object)."""
    s = supersample
    origins, dirs = camera.rays(s)
    points, hit = trace(origins.float(), dirs.float())
    normals = torch.where(hit[:, None], surface_normal(points), torch.zeros_like(points))
    shade = 0.25 + 0.75 * (normals * LIGHT).sum(-1).clamp_min(0)
    colour = torch.where(hit[:, None], albedo(points) * shade[:, None], torch.zeros_like(points))
    h, w = camera.height, camera.width
    alpha = hit.float().reshape(h * w, s * s).mean(1)
    colour = (
        colour.reshape(h * w, s * s, 3).sum(1) / (s * s) / alpha.clamp_min(1e-6)[:, None]
    )  # straight (unpremultiplied)
    normal = F.normalize(normals.reshape(h * w, s * s, 3).sum(1), dim=-1)
    return colour.reshape(h, w, 3), alpha.reshape(h, w), normal.reshape(h, w, 3)


def spiral_cameras(
    count: int, resolution: int, distance: float = 3.2, fov_deg: float = 40.0, phase: float = 0.0
) -> list[Camera]:
    """Cameras on a Fibonacci sphere (elevations -30..75 degrees) looking at the origin, +z up."""
    cameras = []
    golden = math.pi * (3 - math.sqrt(5))
    for i in range(count):
        elevation = math.radians(-30 + 105 * (i + 0.5) / count)
        azimuth = i * golden + phase
        eye = [
            distance * math.cos(elevation) * math.cos(azimuth),
            distance * math.cos(elevation) * math.sin(azimuth),
            distance * math.sin(elevation),
        ]
        cameras.append(
            Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(fov_deg), resolution, resolution)
        )
    return cameras


def analytic_views(
    count: int, resolution: int, prefix: str = "r", phase: float = 0.0
) -> tuple[list[View], list[Tensor]]:
    views, normals = [], []
    for i, camera in enumerate(spiral_cameras(count, resolution, phase=phase)):
        colour, alpha, normal = render_analytic(camera)
        views.append(View(name=f"{prefix}_{i:03d}", image=colour, alpha=alpha, camera=camera))
        normals.append(normal)
    return views, normals


def write_analytic_dataset(root, train_views: int = 40, test_views: int = 8, resolution: int = 128) -> Path:
    """The test object in the Blender layout under `root`, with `{split}/{name}_normal.exr`."""
    root = Path(root)
    splits = {}
    for split, count, phase in (("train", train_views, 0.0), ("test", test_views, 1.0)):
        views, normals = analytic_views(count, resolution, phase=phase)
        splits[split] = views
        for view, normal in zip(views, normals):
            write_raw(root / split / f"{view.name}_normal.exr", normal)
    write_blender(root, splits)
    return root
