"""Decimation to a face budget with quadric edge collapse (fast-simplification, the simplifier PyVista
maintains), keeping the mesh a single closed surface where it was one."""

from __future__ import annotations

import fast_simplification
import numpy as np
import trimesh


def decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """At most `faces` triangles; a mesh already within the budget only loses its zero-area triangles."""
    if len(mesh.faces) <= faces:
        kept = mesh.copy()
        kept.update_faces(kept.nondegenerate_faces())
        kept.remove_unreferenced_vertices()
        return kept
    target = faces
    for _ in range(4):  # the simplifier may stop a little above its target: aim lower until it fits
        points, triangles = fast_simplification.simplify(np.asarray(mesh.vertices, dtype=np.float64),
                                                         np.asarray(mesh.faces, dtype=np.int32), target_count=target)
        if len(triangles) <= faces:
            break
        target = int(target * faces / len(triangles)) - 1
    simplified = trimesh.Trimesh(points, triangles, process=True)
    simplified.remove_unreferenced_vertices()
    return simplified
