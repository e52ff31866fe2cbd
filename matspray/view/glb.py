"""The exported mesh (`matspray export`'s .glb) as a second object beside the Gaussians.

viser draws a .glb with three.js (its glTF loader and standard PBR material): base colour and metallic-roughness
textures and the mesh's normals are shown, lit by viser's own lights and preset environment maps. It cannot light the
mesh with MatSpray's lights (the estimated light, an HDRI, the turn and the exposure apply to the Gaussians only), and
it is drawn by the browser, not by MatSpray's renderer: compare shapes and textures with it, not shading.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from matspray.errors import file_error
from matspray.gltf.model import GLTF_TO_WORLD
from matspray.gltf.read import split_glb
from matspray.view.camera import matrix_to_quaternion

PLACES = ("hidden", "beside", "instead")  # of the Gaussians: not shown, next to them, or in their place


def find_glbs(run_root) -> list[Path]:
    """.glb files in the run folder and its `export/` folder (where people put `matspray export --out`)."""
    root = Path(run_root)
    return sorted(set(root.glob("*.glb")) | set(root.glob("export/*.glb")))


def dataset_from_glb(path: Path, data: bytes) -> np.ndarray:  # -> [4, 4] maps the file's coordinates into the dataset's world
    """The file's frame from its `matspray` extras (`export.frames`); a glb without them is taken as glTF's own Y-up frame,
    which Blender's convention (`GLTF_TO_WORLD`) turns into the dataset's Z-up world."""
    text, _ = split_glb(path, data)
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise file_error(path, f"its glTF JSON does not parse ({exc.msg} at {exc.pos})") from None
    extras = ((document.get("asset") or {}).get("extras") or {}).get("matspray") if isinstance(document, dict) else None
    if isinstance(extras, dict) and "dataset_from_file" in extras:
        matrix = np.asarray(extras["dataset_from_file"], dtype=np.float64).reshape(4, 4)
        if np.isfinite(matrix).all():
            return matrix
    matrix = np.eye(4)
    matrix[:3, :3] = GLTF_TO_WORLD
    return matrix


def glb_pose(matrix: np.ndarray, offset) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a scene node that places the file by `matrix` [4, 4] and then moves it by `offset` [3]."""
    return matrix_to_quaternion(matrix[:3, :3]), matrix[:3, 3] + np.asarray(offset, dtype=np.float64)
