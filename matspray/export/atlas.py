"""A UV atlas with xatlas: charts packed into a square texture with a gutter between them.

Three choices (measured in docs/dev/export.md, "Atlas choices"):
- xatlas drops faces whose area is below float32's epsilon and leaves their UVs at (0, 0); at an object's own
  scale marching cubes makes many of those. The mesh goes in scaled so that an average face has unit area:
  none are dropped (UVs are scale-free).
- Charts are grown on a Taubin-smoothed copy (same topology, positions only): marching-cubes normals are noisy
  and xatlas splits charts wherever normals turn, into many charts of a few faces that blur together at the
  first mip levels.
- Chart growth is capped by boundary length (sqrt(area)), not by xatlas' (slow) iterations; round charts are
  preferred and packed by brute force, which packs tighter; no extra bilinear border beyond the padding."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
import xatlas

from matspray.export.bake import rasterize_uv

SMOOTHING_ITERATIONS = 20  # Taubin passes on the copy the charts are grown on
ROUNDNESS = 6.0  # xatlas' roundness weight (default 0.01): compact charts pack tighter


@dataclass(frozen=True)
class AtlasMesh:
    """The mesh split along the chart seams: every vertex has one UV."""

    positions: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64, counter-clockwise seen from outside
    uvs: np.ndarray  # [V, 2] float64 in [0, 1], glTF convention (v down: row 0 of the texture at v = 0)
    source: np.ndarray  # [V] int64: the vertex of the input mesh each vertex copies
    charts: int = 0  # how many charts xatlas made


def uv_atlas(mesh: trimesh.Trimesh, texture_size: int, padding: int) -> AtlasMesh:
    smooth = mesh.copy()
    trimesh.smoothing.filter_taubin(smooth, iterations=SMOOTHING_ITERATIONS)
    scale = np.sqrt(len(mesh.faces) / max(smooth.area, 1e-30))  # an average face: unit area
    atlas = xatlas.Atlas()
    atlas.add_mesh((np.asarray(smooth.vertices) * scale).astype(np.float32), np.asarray(mesh.faces, dtype=np.uint32))
    charts = xatlas.ChartOptions()
    charts.max_iterations = 0
    charts.max_boundary_length = float(np.sqrt(smooth.area)) * scale
    charts.roundness_weight = ROUNDNESS
    pack = xatlas.PackOptions()
    pack.resolution = texture_size
    pack.padding = padding
    pack.bilinear = False  # the padding already exceeds a bilinear tap; its extra texel cost fill
    pack.bruteForce = True
    atlas.generate(charts, pack)
    vmapping, indices, uvs = atlas[0]
    vmapping = vmapping.astype(np.int64)
    return AtlasMesh(
        np.asarray(mesh.vertices, dtype=np.float64)[vmapping],
        indices.astype(np.int64),
        uvs.astype(np.float64),
        vmapping,
        int(atlas.chart_count),
    )


def uv_areas(uvs: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:  # [V, 2], [F, 3] -> [F] texels^2
    corners = uvs[faces] * size  # [F, 3, 2]
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0])


def atlas_fill(uvs: np.ndarray, faces: np.ndarray, size: int) -> float:
    """Share of the texture's texels whose centre lies on a triangle (what the bake writes, padding excluded)."""
    return len(rasterize_uv(uvs, faces, size).index) / size**2
