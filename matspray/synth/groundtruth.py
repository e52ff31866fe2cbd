"""Ground-truth maps of one view by ray casting the very meshes and textures Mitsuba renders.

Every pixel is sampled on an s x s subpixel grid; a map's value is the mean over the samples that hit
the object (so edge pixels hold the surface's own values, not values darkened by the background),
and `coverage` is the fraction that hit. Textures are read with the same bilinear lookup (UV transform,
wrap modes) at the hit's UV as Mitsuba's bitmap textures, so the maps agree with the renders pixel for pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from matspray.data.camera import Camera
from matspray.synth.materials import Textures, texture_lookup
from matspray.synth.mitsuba_scene import intersect

SAMPLES_PER_SIDE = 4  # 4 x 4 subpixel rays per pixel


@dataclass
class GroundTruth:
    coverage: np.ndarray  # [H, W] fraction of subpixel rays that hit the object
    base_color: np.ndarray  # [H, W, 3] linear, 0 on background
    roughness: np.ndarray  # [H, W], 0 on background
    metallic: np.ndarray  # [H, W], 0 on background
    normal: np.ndarray  # [H, W, 3] unit world-space shading normals, 0 on background
    depth: np.ndarray  # [H, W] camera-space z (OpenCV forward axis), 0 on background


def surface_values(hits, textures: list[Textures]) -> np.ndarray:  # -> [R, 5] base colour, roughness, metallic
    values = np.zeros((len(hits.valid), 5))
    for index, texture in enumerate(textures):
        on_part = hits.part == index
        if not on_part.any():
            continue
        uv = hits.uv[on_part]
        values[on_part, :3] = texture_lookup(texture.base_color, uv, texture.base_color_sampling)
        values[on_part, 3] = texture_lookup(texture.roughness, uv, texture.metallic_roughness_sampling)
        values[on_part, 4] = texture_lookup(texture.metallic, uv, texture.metallic_roughness_sampling)
    return values


def cast_ground_truth(
    scene, textures: list[Textures], camera: Camera, samples_per_side: int = SAMPLES_PER_SIDE
) -> GroundTruth:
    """Ground-truth maps of `camera`'s view of `scene` (built from parts whose textures are `textures`)."""
    origins, directions = camera.rays(samples_per_side)  # [P * s * s, 3] each, grouped by pixel
    origins, directions = origins.double().cpu().numpy(), directions.double().cpu().numpy()
    hits = intersect(scene, origins, directions)
    for index, texture in enumerate(textures):
        if texture.double_sided:  # the back of a double-sided face is shaded with its normal turned round
            back = (hits.part == index) & ((hits.normal * directions).sum(-1) > 0)
            hits.normal[back] *= -1.0
    forward = camera.camtoworld.double().cpu().numpy()[:3, 2]  # OpenCV +z in world space
    per_ray = np.concatenate(
        [surface_values(hits, textures), hits.normal, (hits.distance * (directions @ forward))[:, None]], axis=1
    )  # [R, 9]: base colour 3, roughness, metallic, normal 3, depth
    height, width, samples = camera.height, camera.width, samples_per_side**2
    hit = hits.valid.reshape(height, width, samples).astype(np.float64)
    count = hit.sum(-1)  # [H, W]
    sums = (per_ray.reshape(height, width, samples, -1) * hit[..., None]).sum(2)  # [H, W, 9]
    mean = np.where(count[..., None] > 0, sums / np.maximum(count, 1)[..., None], 0.0)
    normal = mean[..., 5:8]
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(length > 1e-8, normal / np.maximum(length, 1e-8), 0.0)
    return GroundTruth(
        coverage=(count / samples).astype(np.float32),
        base_color=mean[..., :3].astype(np.float32),
        roughness=mean[..., 3].astype(np.float32),
        metallic=mean[..., 4].astype(np.float32),
        normal=normal.astype(np.float32),
        depth=mean[..., 8].astype(np.float32),
    )
