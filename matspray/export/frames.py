"""The two frames an export can be written in. The dataset's world is Z-up (Blender / NeRF-synthetic,
see `render.latlong`); glTF 2.0 is Y-up with +Z towards the viewer. The rotation between them is
Blender's own glTF convention (`matspray.gltf.model.GLTF_TO_WORLD`, the one `synth --asset` reads with):
(x, y, z)_dataset -> (x, z, -y)_glTF."""

from __future__ import annotations

import numpy as np

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
    return {"frame": frame, "up": "+Y" if frame == "gltf" else "+Z",
            "file_from_dataset": forward.tolist(), "dataset_from_file": np.linalg.inv(forward).tolist()}


def dataset_from_file(extras: dict) -> np.ndarray:  # [4, 4] from a file's `extras` written by `frame_extras`
    return np.asarray(extras["dataset_from_file"], dtype=np.float64).reshape(4, 4)
