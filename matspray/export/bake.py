"""Textures from the asset: every texel of the atlas finds its point on the surface, the Gaussians
around that point blend their materials, and empty texels take their nearest filled texel's value (seam
padding that reaches to the texture's edge, so no mip level mixes in a background colour)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from matspray.gaussians import Gaussians

MAX_PAIRS = 1 << 22  # (face, texel) candidates tested at once


@dataclass(frozen=True)
class Texels:
    """The texels whose centres lie on the atlas' triangles."""

    index: np.ndarray  # [T] int64 flat texel index, row * size + column
    face: np.ndarray  # [T] int64 triangle the centre lies in
    bary: np.ndarray  # [T, 3] float64 barycentric coordinates of the centre in that triangle


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
) -> np.ndarray:  # -> [size, size, 5] linear materials, padded over the whole texture
    texels = rasterize_uv(uvs, faces, size)
    points = np.einsum("tk,tkc->tc", texels.bary, positions[faces[texels.face]])  # [T, 3]
    ids, weights = gaussian_weights(points, gaussians, neighbours, min_scale)
    texture = np.zeros((size * size, materials.shape[1]))
    texture[texels.index] = blend(ids, weights, materials)
    filled = np.zeros(size * size, dtype=bool)
    filled[texels.index] = True
    return fill_empty(texture.reshape(size, size, -1), filled.reshape(size, size))
