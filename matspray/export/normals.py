"""Shading normals of the exported surface: the vertex normals of a Taubin-smoothed copy of it.

Marching cubes puts vertices on voxel edges, so the face normals of the fused surface turn in a staircase
pattern one voxel wide, and the decimated mesh keeps much of it: the raw vertex normals ripple. Glossy
material shows every ripple as a wobble in the reflection. Taubin smoothing (a shrinking Laplacian step
followed by an inflating one) removes that high-frequency wobble without shrinking the object, and only
the normals are taken from it: the positions, and so the silhouettes the surface step calibrated, stay."""

from __future__ import annotations

import numpy as np
import trimesh


def smoothed_vertex_normals(mesh: trimesh.Trimesh, iterations: int = 10) -> np.ndarray:  # -> [V, 3]
    """Area-weighted vertex normals [V, 3] (not yet unit: see `unit_normals`) of `mesh` after `iterations`
    Taubin passes (trimesh's lambda 0.5, mu -0.53) on a copy; the mesh itself is left as it is."""
    smooth = trimesh.Trimesh(np.asarray(mesh.vertices, dtype=np.float64).copy(), np.asarray(mesh.faces), process=False)
    if iterations > 0:
        trimesh.smoothing.filter_taubin(smooth, iterations=iterations)
    return np.asarray(smooth.vertex_normals, dtype=np.float64)


def angle_degrees(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [N, 3], [N, 3] -> [N] angle between directions
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-30)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-30)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def unit_normals(normals: np.ndarray, positions: np.ndarray) -> np.ndarray:  # [V, 3], [V, 3] -> [V, 3] unit
    """Vertex normals with the zero-length ones (a vertex whose faces cancel out) replaced by the direction
    from the mesh's centre: glTF requires unit normals."""
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    outward = positions - positions.mean(0)
    outward = outward / np.maximum(np.linalg.norm(outward, axis=-1, keepdims=True), 1e-12)
    outward[np.linalg.norm(outward, axis=-1) < 0.5] = (0.0, 0.0, 1.0)
    return np.where((length > 1e-6) & np.isfinite(length), normals / np.maximum(length, 1e-12), outward)
