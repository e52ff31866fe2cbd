"""Decimation to a face budget with quadric edge collapse (fast-simplification, the simplifier PyVista
maintains), keeping the mesh a single closed surface where it was one."""

from __future__ import annotations

import fast_simplification
import numpy as np
import trimesh


def decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """At most `faces` triangles and none of zero area (a mesh already within the budget only loses those)."""
    if len(mesh.faces) <= faces:
        return without_degenerate(mesh.copy())
    target = faces
    for _ in range(4):  # the simplifier may stop a little above its target: aim lower until it fits
        points, triangles = fast_simplification.simplify(
            np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32), target_count=target
        )
        if len(triangles) <= faces:
            break
        target = int(target * faces / len(triangles)) - 1
    return without_degenerate(trimesh.Trimesh(points, triangles, process=True))


def without_degenerate(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Without zero-area faces and without faces on the same three vertices (a pair of them is a zero-volume
    fin the simplifier can leave behind: xatlas drops both and leaves their UVs at (0, 0)). Dropping every
    copy keeps the rest of the surface closed."""
    mesh.update_faces(mesh.nondegenerate_faces())
    key = np.sort(np.asarray(mesh.faces), axis=1)  # [F, 3]
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    mesh.update_faces(counts[inverse.reshape(-1)] == 1)
    mesh.remove_unreferenced_vertices()
    return mesh
