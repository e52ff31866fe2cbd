"""Render a relightable asset under any environment light: G-buffer rasterization + split-sum shading."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.gbuffer import orient_normals


@dataclass
class Asset:
    """What refinement produces: Gaussians with PBR materials and shading normals."""

    gaussians: Gaussians
    materials: Tensor  # [N, 5] base color rgb (linear), roughness, metallic
    normals: Tensor  # [N, 3] unit; sign is fixed per view when rendering
    visibility: Tensor | None = None  # [N, D] directional visibility (`render.visibility`); None = no shadowing

    def __post_init__(self):
        n = len(self.gaussians)
        if self.materials.shape != (n, 5) or self.normals.shape != (n, 3):
            raise ValueError(f"asset: materials must be [{n}, 5] and normals [{n}, 3], got {tuple(self.materials.shape)}, {tuple(self.normals.shape)}")
        if self.visibility is not None and self.visibility.shape[0] != n:
            raise ValueError(f"asset: visibility must be [{n}, D], got {tuple(self.visibility.shape)}")


def render_gbuffer(asset: Asset, camera: Camera, light=None):
    """Rasterize materials and normals for `camera` -> GBuffer (materials divided by coverage); with a
    `light` and an asset that has visibility, also the shadow factors that light casts."""
    from matspray.render.deferred import GBuffer
    from matspray.render.rasterize import rasterize
    from matspray.render.visibility import gaussian_shadows

    normals = orient_normals(asset.normals, asset.gaussians.means, camera)
    features = [asset.materials, normals]
    if light is not None and asset.visibility is not None:
        features.append(gaussian_shadows(asset.visibility, normals, asset.gaussians.means, asset.materials[:, 3], camera, light))
    out = rasterize(asset.gaussians, camera, torch.cat(features, dim=-1))
    return GBuffer.from_blended(out.features, out.alpha)


def render_relit(asset: Asset, camera: Camera, light, background: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Linear RGB [H, W, 3] of the asset lit by `light` (EnvironmentMap or PrefilteredEnvironment),
    composited over `background` ([3] linear; None = black), and the coverage alpha [H, W]."""
    from matspray.render.deferred import shade_gbuffer

    with torch.no_grad():
        gbuffer = render_gbuffer(asset, camera, light)
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


def background_radiance(light, camera: Camera) -> Tensor:  # -> [H, W, 3] what the camera sees of the environment
    _, dirs = camera.rays()
    return light.radiance(dirs.to(light.map)).reshape(camera.height, camera.width, 3)


def write_video(frames: list[Tensor], path, fps: int) -> None:
    """Frames [H, W, 3] in [0, 1] (sRGB) -> an H.264 MP4 through imageio-ffmpeg's own ffmpeg binary."""
    import os

    import imageio_ffmpeg
    import numpy as np

    from matspray.data.images import atomic_target

    height, width = frames[0].shape[:2]
    tmp = atomic_target(Path(path))
    writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, quality=8, macro_block_size=1)
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray((frame.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()))
    writer.close()
    os.replace(tmp, path)


def relight_run(run_dir, env: str, views: str, out_dir, variant: str = "full", frames: int = 60, fps: int = 24,
                background: str = "transparent", env_height: int = 64) -> list[Path]:
    """Render a run's asset under `env` for the dataset's test cameras or an orbit; returns the files written."""
    from tqdm import tqdm

    from matspray.asset import read_asset
    from matspray.data import load_scene, write_image
    from matspray.data.images import linear_to_srgb
    from matspray.errors import ConfigError, RunError
    from matspray.lights import load_envmap
    from matspray.pipeline import asset_stage
    from matspray.render.envmap import EnvironmentMap
    from matspray.rundir import read_json

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    identity = run_dir / "dataset.json"
    if not identity.exists():
        raise RunError(f"{run_dir}: not a MatSpray run folder (no dataset.json); make one with `matspray run`")
    stage = asset_stage(variant)
    if not (run_dir / stage / "asset.ply").exists():
        raise RunError(f"{run_dir}: no asset for variant '{variant}' ({stage}/asset.ply); run `matspray run --variant {variant}` first")
    if frames < 1 or fps < 1 or env_height < 4:
        raise ConfigError("--frames and --fps must be >= 1 and --env-height >= 4")
    name, env_map = load_envmap(env)
    light = EnvironmentMap.from_tensor(env_map, height=env_height, learnable=False)
    prefiltered = light.prefilter()
    asset = read_asset(run_dir / stage)
    config = read_json(identity)
    scene = load_scene(config["source"], downscale=run_downscale(run_dir))
    if views == "test":
        if not scene.test:
            raise RunError(f"{config['source']}: the dataset has no test views; use --views orbit")
        cameras = [(v.name, v.camera) for v in scene.test]
    else:
        center = scene.bounds.mean(0)
        cameras = [(f"orbit_{i:03d}", c) for i, c in enumerate(orbit_cameras([v.camera for v in scene.train], center, frames))]
    out_dir.mkdir(parents=True, exist_ok=True)
    written, video_frames = [], []
    for view_name, camera in tqdm(cameras, desc=f"relight [{name}]"):
        rgb, alpha = render_relit(asset, camera, prefiltered)
        path = out_dir / f"{view_name}_{name}.png"
        if background == "env":
            rgb = rgb + background_radiance(light, camera) * (1 - alpha[..., None])
            write_image(path, rgb)
        else:
            write_image(path, rgb / alpha[..., None].clamp_min(1e-4), alpha)
        written.append(path)
        video_frames.append(linear_to_srgb(rgb))
    if views == "orbit":
        video = out_dir / f"orbit_{name}.mp4"
        write_video(video_frames, video, fps)
        written.append(video)
    return written


def run_downscale(run_dir: Path) -> float:
    import yaml

    config_path = run_dir / "config.yaml"
    return float(yaml.safe_load(config_path.read_text()).get("downscale", 1.0)) if config_path.exists() else 1.0
