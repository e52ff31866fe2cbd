"""How far the fused surface lies inside the asset's own silhouettes, from the training views.

The TSDF puts the surface where the blended depth is, but that depth averages the stacked splats along each
ray and so sits a little behind the visible surface: on the development objects the marching-cubes mesh lay
~0.009 units (half a voxel) inside the true surface all round and covered 2-5 % fewer test pixels than the
truth and the Gaussians, which the silhouette-counting metric charges for. The silhouettes the asset renders
are what the mesh must reproduce, so the offset is measured against them: the pixels the mesh misses
(or adds) per view, divided by the length of the silhouette's rim, is how far the rim must move."""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from torch import Tensor

from matspray.data.camera import Camera
from matspray.export.bake import rasterize_uv


def mesh_alpha(
    vertices: np.ndarray, faces: np.ndarray, camera: Camera, samples_per_side: int = 1
) -> np.ndarray:  # [V, 3], [F, 3] -> [H, W] float in [0, 1]
    """The share of each pixel the mesh covers (triangles in front of the camera), on an s x s grid of samples
    per pixel (s = 1: the pixel's centre alone), by the UV rasterizer on the projected vertices: a square raster
    of the image's longer side, cropped."""
    s = samples_per_side
    pixels, z = camera.project(torch.as_tensor(vertices, dtype=torch.float32))
    side = max(camera.width, camera.height) * s
    front = (z[faces].min(-1).values > 1e-6).numpy()  # [F] triangles wholly in front
    texels = rasterize_uv(pixels.double().numpy() * s / side, faces[front], side)
    covered = np.zeros(side * side, dtype=bool)  # a byte per sample: 10 MB at 800 px and 4 x 4 samples
    covered[texels.index] = True
    covered = covered.reshape(side, side)[: camera.height * s, : camera.width * s]
    return covered.reshape(camera.height, s, camera.width, s).mean(axis=(1, 3))


def spread(count: int, most: int) -> np.ndarray:  # -> [<= most] int, increasing
    """Up to `most` indices of `count` views, evenly spread from the first to the last."""
    return np.unique(np.linspace(0, count - 1, min(most, count)).round().astype(int)) if count else np.zeros(0, int)


def rim_length(mask: np.ndarray) -> int:  # [H, W] bool -> pixels of the mask with a 4-neighbour outside it
    padded = np.pad(mask, 1)
    inner = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    return int((mask & ~inner).sum())


def silhouette_offset(
    mesh: trimesh.Trimesh, cameras: list[Camera], alphas: list[Tensor], min_alpha: float, views: int = 12
) -> float:
    """World distance (> 0: outwards) to move the surface so that its silhouettes cover as many pixels as the
    asset's (alpha >= min_alpha) in up to `views` of the cameras, spread over them: the summed deficit of
    covered pixels over the summed rim length, in pixels, times a pixel's size at the object's depth."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    picked = spread(len(cameras), views)
    shift, rim = 0.0, 0
    for i in picked:
        camera, target = cameras[i], (alphas[i] >= min_alpha).numpy()
        covered = mesh_alpha(vertices, faces, camera) > 0.5
        _, z = camera.project(torch.as_tensor(vertices, dtype=torch.float32))
        pixel = float(z.median()) / (
            0.5 * float(camera.K[0, 0] + camera.K[1, 1])
        )  # world size of a pixel at the object
        shift += (int(target.sum()) - int(covered.sum())) * pixel
        rim += rim_length(target)
    return shift / rim if rim else 0.0
