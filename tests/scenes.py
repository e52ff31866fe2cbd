"""Tiny scenes made with our own renderer, for tests of the method's stages (not a test module)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import torch

from matspray.data import Camera, View
from matspray.gaussians import Gaussians


def sky_map(height: int = 16) -> torch.Tensor:  # [H, 2H, 3] a bright warm top, a dim cool bottom, one sun
    from matspray.render.shade.latlong import pixel_directions

    d = pixel_directions(height, 2 * height)
    up = d[..., 2:3].clamp_min(0)
    base = torch.tensor([0.25, 0.3, 0.4]) + up * torch.tensor([0.9, 0.8, 0.6])
    sun = torch.exp(
        30 * ((d * torch.nn.functional.normalize(torch.tensor([0.5, 0.3, 0.8]), dim=0)).sum(-1, keepdim=True) - 1)
    )
    return base + 6.0 * sun


def quaternion_z_to(normals: torch.Tensor) -> torch.Tensor:  # [N, 3] unit -> [N, 4] (w, x, y, z) rotating +z onto n
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(normals)
    axis = torch.linalg.cross(z, normals)
    sin = axis.norm(dim=-1, keepdim=True)
    cos = normals[:, 2:3]
    angle = torch.atan2(sin, cos)
    axis = torch.where(sin > 1e-8, axis / sin.clamp_min(1e-8), torch.tensor([1.0, 0.0, 0.0]))
    return torch.cat([torch.cos(angle / 2), axis * torch.sin(angle / 2)], dim=-1)


def sphere_of_disks(n: int = 600, seed: int = 0) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    """Flat opaque disks covering the unit sphere; returns Gaussians, normals [N, 3], materials [N, 5]."""
    g = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    scales = torch.tensor([0.16, 0.16, 0.01]).expand(n, 3)
    gaussians = Gaussians(
        normals.clone(), scales.log(), quaternion_z_to(normals), torch.full((n,), 4.0), torch.zeros(n, 1, 3)
    )
    base = torch.where((normals[:, :1] > 0), torch.tensor([0.7, 0.25, 0.2]), torch.tensor([0.2, 0.35, 0.7]))
    roughness = torch.where(normals[:, 1] > 0, 0.3, 0.8)[:, None]
    metallic = (normals[:, 2] > 0.6).float()[:, None]
    return gaussians, normals, torch.cat([base, roughness, metallic], dim=-1)


def sphere_cameras(count: int, size: int, distance: float = 4.0, turn: float = 0.0) -> list[Camera]:
    """Cameras on a Fibonacci sphere around the origin (every side of the object is seen), the whole set turned
    by `turn` radians about z (another set of views of the same object)."""
    cameras = []
    for i in range(count):
        z = 1 - (2 * i + 1) / count
        azimuth = i * math.pi * (3 - math.sqrt(5)) + turn
        r = math.sqrt(1 - z * z)
        eye = [distance * r * math.cos(azimuth), distance * r * math.sin(azimuth), distance * z]
        cameras.append(Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.75, size, size))
    return cameras


def ring_cameras(count: int, size: int = 32, distance: float = 4.0) -> list[Camera]:
    cameras = []
    for i in range(count):
        azimuth = 2 * math.pi * i / count
        eye = [distance * math.cos(azimuth), distance * math.sin(azimuth), 1.2 * (-1) ** i]
        cameras.append(Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.75, size, size))
    return cameras


def material_scene(n_views: int = 6, size: int = 32, seed: int = 0):
    """Views of the disk sphere lit by `sky_map`, true per-Gaussian materials, and per-view 2D maps
    [H, W, 5] that are the true maps with a different base-color gain per view (like a diffusion model)."""
    from matspray.method.asset import Asset
    from matspray.method.relight import render_gbuffer, render_relit
    from matspray.render.shade.envmap import EnvironmentMap

    gaussians, normals, materials = sphere_of_disks(seed=seed)
    asset = Asset(gaussians, materials, normals)
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    views, maps = [], []
    gains = torch.linspace(0.7, 1.3, n_views)
    for i, camera in enumerate(ring_cameras(n_views, size)):
        rgb, alpha = render_relit(asset, camera, light)
        views.append(
            View(f"r_{i:03d}", rgb / alpha[..., None].clamp_min(1e-4) * (alpha[..., None] > 1e-4), alpha, camera)
        )
        gbuffer = render_gbuffer(asset, camera)
        base = (gbuffer.base_color * gains[i]).clamp(0, 1)
        maps.append(
            torch.cat([base, gbuffer.roughness[..., None], gbuffer.metallic[..., None]], dim=-1).clamp(0, 1).detach()
        )
    return gaussians, normals, materials, views, maps


def lift_material_scene(gaussians: Gaussians, views: list[View], maps: list[torch.Tensor]):
    """`material_scene`'s 2D maps lifted onto its Gaussians, 2 x 2 rays per pixel (a LiftResult)."""
    from matspray.method.lift import LiftConfig, lift

    cameras, masks, names = [v.camera for v in views], [v.alpha for v in views], [v.name for v in views]
    return lift(gaussians, cameras, maps, masks, names, LiftConfig(samples_per_side=2), progress=False)


def write_disk_sphere_run(root, gaussians: int, cameras: list[Camera], train: slice, test: slice):
    """A run folder `root/run` holding the disk sphere's asset (true materials, the sky light as its estimated
    light) and a Blender dataset `root/data` of its renders at `cameras` (the `train` and `test` slices of them);
    returns the run folder."""
    from matspray.data.formats.blender import write_blender
    from matspray.method.asset import Asset, write_asset
    from matspray.method.refine.loop import RefineResult
    from matspray.method.relight import render_relit
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.rundir import write_json

    g, normals, materials = sphere_of_disks(gaussians)
    asset = Asset(g, materials, normals)
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False)
    prefiltered = light.prefilter()
    views = []
    for i, camera in enumerate(cameras):
        rgb, alpha = render_relit(asset, camera, prefiltered)
        views.append(View(f"r_{i:03d}", rgb / alpha[..., None].clamp_min(1e-4), alpha, camera))
    write_blender(root / "data", {"train": views[train], "test": views[test]})
    run = root / "run"
    run.mkdir(parents=True)
    write_json(run / "dataset.json", {"source": str(root / "data"), "format": "blender"})
    write_asset(run / "asset", g, RefineResult(materials, normals, source=None, envmap=light, history=[]))
    return run


def stacked_opaque_gaussians(n: int = 8) -> tuple[Gaussians, Camera, torch.Tensor]:
    """`n` nearly opaque Gaussians (opacity 0.95) stacked on the optical axis of an 8 x 8 camera, one feature channel
    each: blending stops before the farthest ones once the transmittance would fall below 1e-4."""
    means = torch.zeros(n, 3)
    means[:, 2] = torch.linspace(-0.5, 0.5, n)
    gaussians = Gaussians(
        means,
        torch.full((n, 3), math.log(0.3)),
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.logit(torch.full((n,), 0.95)),
        torch.zeros(n, 1, 3),
    )
    camera = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], math.radians(30), 8, 8)
    return gaussians, camera, torch.eye(n)


def capture_like(dataset: Path, out: Path) -> Path:
    """A synthetic object's photos and cameras alone: what structure from motion leaves, no ground truth."""
    out.mkdir()
    for name in ("transforms_train.json", "transforms_test.json"):
        shutil.copy2(dataset / name, out / name)
    for split in ("train", "test"):
        (out / split).mkdir()
        for photo in (dataset / split).glob("r_[0-9][0-9][0-9].png"):
            shutil.copy2(photo, out / split / photo.name)
    return out
