"""Textures from the asset: every texel of the atlas finds its point on the surface and takes the materials the
asset shows there: its rendered material maps at the training views that see the point (what every render of the
Gaussians composites), else the Gaussians around the point blended in 3D. Empty texels take their nearest filled
texel's value (seam padding that reaches to the texture's edge, so no mip level mixes in a background colour)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.raster.rasterize import rasterize

MAX_PAIRS = 1 << 22  # (face, texel) candidates tested at once
# A view's weight is its cosine to the texel to this power: the most frontal views, whose pixels lie closest to the
# texel's own spot, dominate (docs/defaults.md)
VIEW_POWER = 8


@dataclass(frozen=True)
class Texels:
    """The texels whose centres lie on the atlas' triangles."""

    index: np.ndarray  # [T] int64 flat texel index, row * size + column
    face: np.ndarray  # [T] int64 triangle the centre lies in
    bary: np.ndarray  # [T, 3] float64 barycentric coordinates of the centre in that triangle


def sample_bilinear(image: Tensor, pixels: Tensor) -> Tensor:  # [H, W, C], [P, 2] continuous (x, y) -> [P, C]
    """Bilinear lookup with pixel centres at +0.5, clamped to the border."""
    h, w = image.shape[:2]
    x = (pixels[:, 0] - 0.5).clamp(0, w - 1)
    y = (pixels[:, 1] - 0.5).clamp(0, h - 1)
    x0, y0 = x.floor().long().clamp(max=w - 2 if w > 1 else 0), y.floor().long().clamp(max=h - 2 if h > 1 else 0)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def rasterize_uv(uvs: np.ndarray, faces: np.ndarray, size: int) -> Texels:  # [V, 2] in [0, 1], [F, 3]
    """Texels (centres at +0.5) covered by the triangles of a UV layout (u -> column, v -> row)."""
    corners = uvs[faces] * size  # [F, 3, 2] pixel coordinates
    lo = np.clip(np.ceil(corners.min(1) - 0.5), 0, size - 1).astype(np.int64)  # [F, 2] first centre inside the box
    hi = np.clip(np.floor(corners.max(1) - 0.5), -1, size - 1).astype(np.int64)
    extent = np.maximum(hi - lo + 1, 0)  # [F, 2]
    counts = extent[:, 0] * extent[:, 1]
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (
        c[:, 0] - a[:, 0]
    )  # [F] twice the signed area
    counts[np.abs(area) < 1e-12] = 0
    found_index, found_face, found_bary = [], [], []
    ends = np.cumsum(counts)
    start = 0
    while start < len(faces):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + MAX_PAIRS, side="right"))
        stop = max(stop, start + 1)
        ids = np.arange(start, stop)
        face = np.repeat(ids, counts[ids])
        local = np.arange(len(face)) - np.repeat(np.cumsum(counts[ids]) - counts[ids], counts[ids])
        col = lo[face, 0] + local % np.maximum(extent[face, 0], 1)
        row = lo[face, 1] + local // np.maximum(extent[face, 0], 1)
        p = np.stack([col + 0.5, row + 0.5], axis=-1)  # [P, 2]
        pa, pb, pc = a[face], b[face], c[face]
        w_a = ((pb[:, 0] - p[:, 0]) * (pc[:, 1] - p[:, 1]) - (pb[:, 1] - p[:, 1]) * (pc[:, 0] - p[:, 0])) / area[face]
        w_b = ((pc[:, 0] - p[:, 0]) * (pa[:, 1] - p[:, 1]) - (pc[:, 1] - p[:, 1]) * (pa[:, 0] - p[:, 0])) / area[face]
        bary = np.stack([w_a, w_b, 1.0 - w_a - w_b], axis=-1)
        inside = (bary >= -1e-9).all(-1)
        found_index.append(row[inside] * size + col[inside])
        found_face.append(face[inside])
        found_bary.append(bary[inside])
        start = stop
    if not found_index:  # no triangles
        return Texels(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    # a centre on a shared edge: the first triangle keeps it
    index, first = np.unique(np.concatenate(found_index), return_index=True)
    return Texels(index, np.concatenate(found_face)[first], np.concatenate(found_bary)[first])


def gaussian_weights(
    points: np.ndarray,  # [P, 3]
    gaussians: Gaussians,
    neighbours: int,
    min_scale: float,  # Gaussians are widened to at least this standard deviation on every axis
    chunk: int = 1 << 16,
) -> tuple[np.ndarray, np.ndarray]:  # -> ids [P, k] int64, weights [P, k] summing to 1
    """How much each of the `neighbours` nearest Gaussians (by centre) contributes at each point: its
    opacity times its (widened) density there, normalised. A point no Gaussian reaches takes its nearest."""
    means = gaussians.means.detach().cpu().double().numpy()
    k = min(neighbours, len(means))
    _, ids = cKDTree(means).query(points, k=k)
    ids = np.asarray(ids, dtype=np.int64).reshape(len(points), k)
    rotations = gaussians.rotation_matrices().detach().cpu().double().numpy()  # [N, 3, 3] columns = local axes
    scales = np.maximum(gaussians.scales.detach().cpu().double().numpy(), min_scale)  # [N, 3]
    opacity = gaussians.opacities.detach().cpu().double().numpy()  # [N]
    weights = np.empty((len(points), k))
    for s in range(0, len(points), chunk):
        i = ids[s : s + chunk]  # [p, k]
        offset = points[s : s + chunk, None, :] - means[i]  # [p, k, 3]
        local = np.einsum("pkji,pkj->pki", rotations[i], offset) / scales[i]  # [p, k, 3]
        weights[s : s + chunk] = opacity[i] * np.exp(-0.5 * (local**2).sum(-1))
    total = weights.sum(-1, keepdims=True)
    lonely = total[:, 0] < 1e-12
    weights[lonely] = 0.0
    weights[lonely, 0] = 1.0
    return ids, weights / np.where(lonely[:, None], 1.0, total)


def blend(ids: np.ndarray, weights: np.ndarray, values: np.ndarray) -> np.ndarray:  # [P, k], [P, k], [N, C] -> [P, C]
    return np.einsum("pk,pkc->pc", weights, values[ids])


def blend_normals(
    ids: np.ndarray,  # [P, k] Gaussians near each point
    weights: np.ndarray,  # [P, k] their weights, summing to 1
    normals: np.ndarray,  # [N, 3] the Gaussians' unoriented unit normals
    reference: np.ndarray,  # [P, 3] the surface's own unit normals
    share: float = 1.0,  # the Gaussians' share of the result
) -> np.ndarray:  # -> [P, 3] unit
    """The Gaussians' normals, each flipped to the side of `reference` first, blended; then mixed with
    `reference` at `share` (1: the Gaussians' alone). Falls back to `reference` where the flips cancel out."""
    picked = normals[ids]  # [P, k, 3]
    sign = np.where(np.einsum("pkc,pc->pk", picked, reference) < 0, -1.0, 1.0)
    summed = np.einsum("pk,pkc->pc", weights * sign, picked)
    length = np.linalg.norm(summed, axis=-1, keepdims=True)
    gaussian = np.where(length > 1e-6, summed / np.maximum(length, 1e-12), reference)
    mixed = share * gaussian + (1 - share) * reference  # both unit and on one side: never zero
    return mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)


@dataclass(frozen=True)
class ViewBake:
    """Where the textures are read from the asset's renders: the cameras, and how far (world units) a texel may lie
    from the rendered depth and still count as seen (further: something else is in front of it)."""

    cameras: list[Camera]
    depth_tolerance: float
    min_alpha: float  # rendered coverage below which a pixel shows no surface


def view_materials(
    points: np.ndarray,  # [T, 3] texel positions on the mesh
    normals: np.ndarray,  # [T, 3] unit outward normals there
    gaussians: Gaussians,
    materials: Tensor,  # [N, C] the Gaussians' materials
    views: ViewBake,
) -> tuple[np.ndarray, np.ndarray]:  # -> [T, C] the views' weighted mean, [T] their total weight (0: unseen)
    """Each texel's materials as the asset renders them: per camera, the alpha-composited material maps read where
    the texel projects, where the rendered depth agrees with the texel's, weighted by the view's cosine to
    `VIEW_POWER`."""
    points_t = torch.as_tensor(points, dtype=torch.float32)
    normals_t = torch.as_tensor(normals, dtype=torch.float32)
    sums, total = torch.zeros(len(points), materials.shape[1], dtype=torch.float64), torch.zeros(len(points))
    colours = materials.to(gaussians.device, torch.float32)
    with torch.no_grad():
        for camera in views.cameras:
            raster = rasterize(gaussians, camera.to(colours.device), colours)
            alpha = raster.alpha[..., None]  # [H, W, 1]
            maps = torch.cat([raster.features / alpha.clamp_min(1e-6), raster.expected_depth[..., None], alpha], -1)
            camera = camera.to("cpu")
            pixels, z = camera.project(points_t)  # [T, 2], [T]
            sampled = sample_bilinear(maps.cpu(), pixels)  # [T, C + 2]: materials, depth, alpha
            toward = torch.nn.functional.normalize(camera.center[None] - points_t, dim=-1)
            cosine = (normals_t * toward).sum(-1)
            seen = camera.in_image(pixels, z) & (cosine > 0) & (sampled[:, -1] > views.min_alpha)
            seen &= (sampled[:, -2] - z).abs() < views.depth_tolerance
            weight = torch.where(seen, cosine**VIEW_POWER, torch.zeros_like(cosine))  # seen: cosine > 0
            sums += weight[:, None].double() * sampled[:, :-2].double()
            total += weight
    mean = sums / total.clamp_min(1e-12)[:, None].double()
    return mean.numpy(), total.numpy()


def fill_empty(texture: np.ndarray, filled: np.ndarray) -> np.ndarray:  # [S, S, C], [S, S] bool -> [S, S, C]
    """Every texel that no triangle covers takes the value of the nearest covered texel."""
    if filled.all() or not filled.any():
        return texture
    nearest = distance_transform_edt(~filled, return_distances=False, return_indices=True)  # [2, S, S]
    return texture[nearest[0], nearest[1]]


def bake_textures(
    positions: np.ndarray,  # [V, 3] mesh vertices, dataset frame
    faces: np.ndarray,  # [F, 3]
    uvs: np.ndarray,  # [V, 2]
    gaussians: Gaussians,
    materials: np.ndarray,  # [N, 5] linear base colour rgb, roughness, metallic
    size: int,
    neighbours: int,
    min_scale: float,
    views: ViewBake | None = None,  # None: every texel from the Gaussians around it
) -> np.ndarray:  # -> [size, size, 5] linear materials, padded over the whole texture
    texels = rasterize_uv(uvs, faces, size)
    points = np.einsum("tk,tkc->tc", texels.bary, positions[faces[texels.face]])  # [T, 3]
    values = np.zeros((len(points), materials.shape[1]))
    unseen = np.ones(len(points), dtype=bool)
    if views is not None and views.cameras:
        normals = trimesh.Trimesh(positions, faces, process=False).face_normals[texels.face]
        values, weight = view_materials(points, normals, gaussians, torch.from_numpy(materials), views)
        unseen = weight <= 0
    if unseen.any():
        ids, weights = gaussian_weights(points[unseen], gaussians, neighbours, min_scale)
        values[unseen] = blend(ids, weights, materials)
    texture = np.zeros((size * size, materials.shape[1]))
    texture[texels.index] = values
    filled = np.zeros(size * size, dtype=bool)
    filled[texels.index] = True
    return fill_empty(texture.reshape(size, size, -1), filled.reshape(size, size))
