"""Normals of flat Gaussians: per-Gaussian shortest axes, rendered normal maps, normals of a depth map."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.images import resize
from matspray.gaussians import Gaussians
from matspray.render.backend import compiled_on_cpu
from matspray.render.raster.gbuffer import orient_normals
from matspray.render.raster.rasterize import rasterize


def shortest_axes(gaussians: Gaussians) -> Tensor:  # [N, 3] unit, unoriented; differentiable w.r.t. quats
    return gaussians.normals()


def oriented_normals(gaussians: Gaussians, camera: Camera) -> Tensor:  # [N, 3] unit
    """Each Gaussian's shortest axis, flipped to face `camera` (the side the camera sees). Within a block that renders
    with numba, on the CPU, by compiled loops (matspray.render.numba.normals), which training calls every step."""
    if compiled_on_cpu(gaussians.means.device):
        from matspray.render.numba.normals import CompiledNormals  # numba loads where it renders

        return CompiledNormals.apply(gaussians.quats, gaussians.log_scales, gaussians.means, camera.center)
    return orient_normals(shortest_axes(gaussians), gaussians.means, camera)


def consensus_normals(gaussians: Gaussians, cameras: list[Camera]) -> Tensor:  # [N, 3] unit
    """Shortest axes oriented once for all views: towards the side from which the Gaussian contributes
    most to the training images. A Gaussian's blending weight summed over a view's pixels is the
    gradient of the rendered alpha sum w.r.t. a zero feature, so one backward pass per view gives it."""
    g = gaussians.detach()
    axes = shortest_axes(g)
    vote = torch.zeros(len(g), dtype=axes.dtype, device=axes.device)
    for camera in cameras:
        probe = torch.zeros(len(g), 1, dtype=axes.dtype, device=axes.device, requires_grad=True)
        out = rasterize(g, camera, probe)
        (weights,) = torch.autograd.grad(out.features.sum(), probe)
        facing = torch.sign((axes * (camera.center.to(axes) - g.means)).sum(-1))
        vote += weights[:, 0] * facing
    return axes * torch.where(vote < 0, -1.0, 1.0).to(axes)[:, None]


def depth_normals(depth: Tensor, camera: Camera) -> Tensor:  # [H, W] -> [H, W, 3] world, unit; zero on the border
    """Normals of the surface described by a z-depth map: cross product of central differences of the
    back-projected points, oriented towards the camera."""
    return depth_normals_along(depth, camera.pixel_directions().to(depth), camera.center.to(depth))


def depth_normals_along(
    depth: Tensor,  # [H, W] camera z
    directions: Tensor,  # [H, W, 3] Camera.pixel_directions()
    center: Tensor,  # [3] the camera's position
) -> Tensor:  # [H, W, 3] world, unit; zero on the border
    """`depth_normals` from the camera's pixel rays: tensors only, as training's loss terms take it."""
    points = center + directions * depth[..., None]
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    normals = F.normalize(torch.linalg.cross(dy, dx, dim=-1), dim=-1)
    to_camera = center - points[1:-1, 1:-1]
    normals = torch.where((normals * to_camera).sum(-1, keepdim=True) < 0, -normals, normals)
    return F.pad(normals.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)


def resize_normal_map(normals: Tensor, height: int, width: int) -> Tensor:  # [H, W, 3] -> [height, width, 3]
    """A normal map (unit, zero where there is none) at another size: area-averaged (bilinear when enlarged) and
    normalised again; a pixel that averages more "none" than normals is none."""
    if normals.shape[:2] == (height, width):
        return normals
    resized = resize(normals, height, width, mode="box")
    coverage = resize((normals.norm(dim=-1) > 0.5).to(normals), height, width, mode="box")
    return torch.where((coverage > 0.5)[..., None], F.normalize(resized, dim=-1), torch.zeros_like(resized))


def render_normals(gaussians: Gaussians, camera: Camera) -> tuple[Tensor, Tensor]:
    """Normal map [H, W, 3] (world, unit where covered, zero elsewhere) and alpha [H, W]."""
    out = rasterize(gaussians, camera, oriented_normals(gaussians, camera))
    return F.normalize(out.features, dim=-1), out.alpha


def normal_map_to_rgb(normals: Tensor) -> Tensor:  # [H, W, 3] unit -> [H, W, 3] in [0, 1] (n + 1) / 2
    return (normals * 0.5 + 0.5).clamp(0.0, 1.0)


def angular_error_degrees(a: Tensor, b: Tensor) -> Tensor:  # [..., 3], [..., 3] -> [...]
    cos = (F.normalize(a, dim=-1) * F.normalize(b, dim=-1)).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))
