"""Render a relightable asset under any environment light: G-buffer rasterization + split-sum shading.
Only rendering: reading run folders and writing files is the CLI's (`matspray.cli.relight`)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.method.asset import Asset
from matspray.method.refine.camera_light import CameraLight, falloff
from matspray.render.raster.gbuffer import orient_normals
from matspray.render.raster.rasterize import rasterize
from matspray.render.shade.brdf import camera_light_radiance
from matspray.render.shade.deferred import GBuffer, shade_gbuffer, view_directions
from matspray.render.shade.visibility import gaussian_shadows


def render_gbuffer(asset: Asset, camera: Camera, light=None):
    """Rasterize materials and normals for `camera` -> GBuffer (materials divided by coverage); with a
    `light` and an asset that has visibility, also the shadow factors that light casts."""
    normals = orient_normals(asset.normals, asset.gaussians.means, camera)
    features = [asset.materials, normals]
    if light is not None and asset.visibility is not None:
        features.append(
            gaussian_shadows(asset.visibility, normals, asset.gaussians.means, asset.materials, camera, light)
        )
    out = rasterize(asset.gaussians, camera, torch.cat(features, dim=-1))
    return GBuffer.from_blended(out.features, out.alpha)


def render_relit(
    asset: Asset, camera: Camera, light, background: Tensor | None = None, camera_light: CameraLight | None = None
) -> tuple[Tensor, Tensor]:
    """Linear RGB [H, W, 3] of the asset lit by `light` (EnvironmentMap or PrefilteredEnvironment), and by a flash at
    the camera with `camera_light` (a capture's photo as refinement explained it), composited over `background` ([3]
    linear; None = black), and the coverage alpha [H, W]."""
    with torch.no_grad():
        gbuffer = render_gbuffer(asset, camera, light)
        rgb = shade_gbuffer(gbuffer, camera, light, background)
        if camera_light is not None:
            rgb = rgb + flash_radiance(asset, camera, gbuffer, camera_light) * gbuffer.alpha[..., None]
        return rgb, gbuffer.alpha


def flash_radiance(asset: Asset, camera: Camera, gbuffer: GBuffer, camera_light: CameraLight) -> Tensor:  # [H, W, 3]
    """What a flash at `camera` adds to each pixel of its G-buffer (`brdf.camera_light_radiance`), its distance the
    Gaussians' blended distance to the camera, as refinement computes it (`refine.training.TrainingViews`)."""
    distances = (asset.gaussians.means - camera.center.to(asset.gaussians.means)).norm(dim=-1, keepdim=True)
    out = rasterize(asset.gaussians, camera, distances)  # [H, W, 1]
    irradiance = falloff(out.features[..., 0], out.alpha, camera_light.reference_distance) * camera_light.intensity
    wo = view_directions(camera, gbuffer.normals.device, gbuffer.normals.dtype)
    return camera_light_radiance(
        gbuffer.base_color, gbuffer.roughness, gbuffer.metallic, gbuffer.normals, wo, irradiance
    )


def orbit_cameras(reference: list[Camera], target: Tensor, frames: int = 60, up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """Cameras circling `target` [3] about the `up` axis, at the mean distance and elevation of the
    reference cameras and with their focal lengths and image size (principal point at the centre). The first frame
    looks from the side of the first reference camera."""
    target = torch.as_tensor(target, dtype=torch.float64)
    distance, elevation, first_axis, second_axis, up_axis = orbit_basis(reference, target, up)
    first = reference[0]
    cameras = []
    for i in range(frames):
        azimuth = 2 * math.pi * i / frames
        direction = (
            math.cos(elevation) * (math.cos(azimuth) * first_axis + math.sin(azimuth) * second_axis)
            + math.sin(elevation) * up_axis
        )
        camera = Camera.look_at(target + distance * direction, target, up_axis, first.fov_x, first.width, first.height)
        camera.K = first.K.clone()
        # the principal point at the centre, so that the target is: a photo cut to its object (matspray.data.crop)
        # has it far off
        camera.K[0, 2], camera.K[1, 2] = first.width / 2, first.height / 2
        cameras.append(camera)
    return cameras


def orbit_basis(reference: list[Camera], target: Tensor, up) -> tuple[float, float, Tensor, Tensor, Tensor]:
    """The circle `orbit_cameras` turns on: the reference cameras' mean distance from `target` [3] and mean elevation
    (radians) above the plane normal to `up`, and that plane's axes (towards the first camera, and its right angle)
    with the unit up axis, [3] float64 each."""
    target = torch.as_tensor(target, dtype=torch.float64)
    up_axis = F.normalize(torch.as_tensor(up, dtype=torch.float64), dim=0)
    offsets = torch.stack([c.center.double() - target for c in reference])
    distance = float(offsets.norm(dim=-1).mean())
    elevation = float(torch.asin((F.normalize(offsets, dim=-1) @ up_axis).clamp(-0.99, 0.99)).mean())
    side = offsets[0] - (offsets[0] @ up_axis) * up_axis
    if float(side.norm()) < 1e-9 * max(distance, 1e-12):  # the first camera looks straight down the axis
        side = torch.linalg.svd(up_axis[None]).Vh[1]
    first_axis = F.normalize(side, dim=0)
    return distance, elevation, first_axis, torch.linalg.cross(up_axis, first_axis), up_axis


def orbit_spec(reference: list[Camera], target: Tensor, up) -> dict:
    """`orbit_cameras`' circle as plain numbers, for a file or a page: centre, up, the plane's axes (first, second),
    distance, elevation (radians), and the first reference camera's focal lengths and image size."""
    distance, elevation, first_axis, second_axis, up_axis = orbit_basis(reference, target, up)
    first = reference[0]
    return {
        "center": [float(x) for x in torch.as_tensor(target, dtype=torch.float64)],
        "up": up_axis.tolist(),
        "first": first_axis.tolist(),
        "second": second_axis.tolist(),
        "distance": distance,
        "elevation": elevation,
        "fx": float(first.K[0, 0]),
        "fy": float(first.K[1, 1]),
        "width": int(first.width),
        "height": int(first.height),
    }


def spec_cameras(spec: dict, frames: int) -> list[Camera]:
    """The orbit `orbit_spec` describes, `frames` cameras of it (the same as `orbit_cameras` of its references)."""
    center, up, first = (torch.tensor(spec[k], dtype=torch.float64) for k in ("center", "up", "first"))
    elevation, width, height = spec["elevation"], spec["width"], spec["height"]
    eye = center + spec["distance"] * (math.cos(elevation) * first + math.sin(elevation) * up)
    reference = Camera.look_at(eye, center, up, 2 * math.atan(width / (2 * spec["fx"])), width, height)
    reference.K[1, 1] = spec["fy"]
    return orbit_cameras([reference], center, frames, up)


def cameras_up(cameras: list[Camera]) -> Tensor:  # -> [3] unit, float64
    """The world direction the cameras hold as up (the mean of their image-up axes): a capture's up, whatever
    frame its poses came in (structure from motion picks an arbitrary one)."""
    ups = torch.stack([-c.camtoworld[:3, 1].double() for c in cameras])  # OpenCV axes: image up is camera -y
    return F.normalize(ups.mean(0), dim=0)


def background_radiance(light, camera: Camera) -> Tensor:  # -> [H, W, 3] what the camera sees of the environment
    _, dirs = camera.rays()
    return light.radiance(dirs.to(light.map)).reshape(camera.height, camera.width, 3)
