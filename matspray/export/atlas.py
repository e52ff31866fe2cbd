"""A UV atlas with xatlas: charts packed into a square texture with a gutter between them.

Three choices, each measured on a 50k-face surface of a demo-preset asset (dev-00, 1024 px):
- xatlas drops faces whose area is below float32's epsilon (1.2e-7) and leaves their UVs at (0, 0): on the
  object's own scale (~2 units) marching cubes makes hundreds of those (644 zero-area UV faces on main).
  The mesh goes in scaled so that an average face has unit area: none are dropped (UVs are scale-free).
- Charts are grown on a Taubin-smoothed copy (same topology, positions only): marching-cubes normals are
  noisy and xatlas splits charts wherever normals turn, 1 439 charts of a few faces each (texture 30 %
  filled, charts blurred together at the first mip levels); smoothed, 112-121 charts.
- Chart growth is capped by boundary length (sqrt(area)), not by xatlas' iterations (those took 50-100 s),
  round charts are preferred (roundness weight 4) and packed by brute force: fill 52 % in 8 s."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
import xatlas

SMOOTHING_ITERATIONS = 20  # Taubin passes on the copy the charts are grown on
ROUNDNESS = 4.0  # xatlas' roundness weight (default 0.01): compact charts pack tighter (2: 47.7 %, 4: 52.2 % fill on dev-00)


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
    pack.bilinear = True
    pack.bruteForce = True
    atlas.generate(charts, pack)
    vmapping, indices, uvs = atlas[0]
    vmapping = vmapping.astype(np.int64)
    return AtlasMesh(np.asarray(mesh.vertices, dtype=np.float64)[vmapping], indices.astype(np.int64), uvs.astype(np.float64), vmapping,
                     int(atlas.chart_count))


def uv_areas(uvs: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:  # [V, 2], [F, 3] -> [F] texels^2
    corners = uvs[faces] * size  # [F, 3, 2]
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    return 0.5 * np.abs(edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0])


def atlas_fill(uvs: np.ndarray, faces: np.ndarray, size: int) -> float:
    """Share of the texture's texels whose centre lies on a triangle (what the bake writes, padding excluded)."""
    from matspray.export.bake import rasterize_uv

    return len(rasterize_uv(uvs, faces, size).index) / size**2
