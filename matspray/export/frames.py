"""The two frames an export can be written in. The dataset's world is Z-up (Blender / NeRF-synthetic,
see `render.latlong`); glTF 2.0 is Y-up with +Z towards the viewer. The rotation between them is
Blender's own glTF convention (`matspray.gltf.model.GLTF_TO_WORLD`, the one `synth --asset` reads with):
(x, y, z)_dataset -> (x, z, -y)_glTF."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from matspray.errors import file_error
from matspray.gltf.document import split_glb
from matspray.gltf.model import GLTF_TO_WORLD

GLTF_FROM_DATASET = np.eye(4)
GLTF_FROM_DATASET[:3, :3] = GLTF_TO_WORLD.T  # [4, 4] the inverse rotation


def file_from_dataset(frame: str) -> np.ndarray:  # -> [4, 4] maps dataset points to the file's coordinates
    return GLTF_FROM_DATASET.copy() if frame == "gltf" else np.eye(4)


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:  # [4, 4], [P, 3] -> [P, 3]
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_directions(matrix: np.ndarray, directions: np.ndarray) -> np.ndarray:  # [4, 4], [P, 3] -> [P, 3] (rigid)
    return directions @ matrix[:3, :3].T


def frame_extras(frame: str) -> dict:
    """What the file's `extras` record: its frame and the 4x4 matrices (row-major) both ways."""
    forward = file_from_dataset(frame)
    return {
        "frame": frame,
        "up": "+Y" if frame == "gltf" else "+Z",
        "file_from_dataset": forward.tolist(),
        "dataset_from_file": np.linalg.inv(forward).tolist(),
    }


def dataset_from_file(extras: dict) -> np.ndarray:  # [4, 4] from a file's `extras` written by `frame_extras`
    return np.asarray(extras["dataset_from_file"], dtype=np.float64).reshape(4, 4)


def find_glbs(run_root) -> list[Path]:
    """.glb files in the run folder and its `export/` folder (where people put `matspray export --out`)."""
    root = Path(run_root)
    return sorted(set(root.glob("*.glb")) | set(root.glob("export/*.glb")))


def dataset_from_glb(
    path: Path, data: bytes
) -> np.ndarray:  # -> [4, 4] maps the file's coordinates into the dataset's world
    """The file's frame from its `matspray` extras (`export.frames`); a glb without them is taken as glTF's own Y-up
    frame, which Blender's convention (`GLTF_TO_WORLD`) turns into the dataset's Z-up world."""
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


def glb_box(path: Path) -> tuple[list[float], list[float]]:
    """The axis-aligned box ([3] low, [3] high) of an exported glb's vertices in the dataset's world."""
    import trimesh

    mesh = trimesh.load(path, force="mesh")
    points = transform_points(
        dataset_from_glb(path, Path(path).read_bytes()), np.asarray(mesh.vertices, dtype=np.float64)
    )
    return points.min(0).tolist(), points.max(0).tolist()
