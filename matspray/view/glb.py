"""The exported mesh (`matspray export`'s .glb) as a second object beside the Gaussians.

viser draws a .glb with three.js (its glTF loader and standard PBR material): base colour and metallic-roughness
textures and the mesh's normals are shown, lit by viser's own lights and preset environment maps. It cannot light the
mesh with MatSpray's lights (the estimated light, an HDRI, the turn and the exposure apply to the Gaussians only), and
it is drawn by the browser, not by MatSpray's renderer: compare shapes and textures with it, not shading.
"""

from __future__ import annotations

import numpy as np

from matspray.view.camera import matrix_to_quaternion

PLACES = ("hidden", "beside", "instead")  # of the Gaussians: not shown, next to them, or in their place


def glb_pose(matrix: np.ndarray, offset) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a scene node that places the file by `matrix` [4, 4] and then moves it by `offset` [3]."""
    return matrix_to_quaternion(matrix[:3, :3]), matrix[:3, 3] + np.asarray(offset, dtype=np.float64)
