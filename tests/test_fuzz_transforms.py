"""Property-based tests of the transforms readers: corrupt a valid Blender `transforms_train.json` or nerfstudio
`transforms.json` the way a careless exporter or a typo would (a field of the wrong type, NaN/Inf, zero or
negative, wrong shapes, dropped fields, scaled/sheared/singular poses, missing files), then load it.

Either load_scene refuses with a MatsprayError whose one-line message names a file of the dataset, or it
returns a Scene that training can use (`check_scene`). Anything else, a traceback, is a bug in a reader.
"""

from __future__ import annotations

import copy
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from matspray.data import load_scene
from matspray.data.scene import Scene
from matspray.errors import MatsprayError
from tests.fuzzing import read_or_refuse
from tests.test_captures import one_frame
from tests.test_readers import blender_folder

# derandomize: every run tries the same cases; database=None: no example store left behind, nothing replayed from one
FUZZ = settings(
    max_examples=200, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow]
)

CAMERA_FIELDS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
FRAME_FIELDS = ("file_path", "transform_matrix", "mask_path", "camera_model", "k1", "p1", *CAMERA_FIELDS)

# values of the wrong type, out of range or extreme, as a typo or a careless exporter writes them
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.sampled_from([10**400, -(10**400)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 0.0, -0.0, 1e-320, 1e300, -1.0]),
    st.text(max_size=6),
    st.sampled_from(["50", "0.8", "nan", "inf", "-1", "1e999", "fifty"]),
)
values = st.one_of(
    scalars,
    st.lists(scalars, max_size=5),
    st.dictionaries(st.text(max_size=3), scalars, max_size=2),
    st.lists(st.lists(scalars, min_size=4, max_size=4), min_size=3, max_size=5),
)


def pose_edits():
    """A 4x4 matrix a pose is multiplied by: scale, shear, mirror, singular or arbitrary."""
    scale = st.floats(min_value=-10, max_value=10).map(lambda s: np.diag([s, s, s, 1.0]))
    shear = st.floats(min_value=-2, max_value=2).map(
        lambda k: np.array([[1, k, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    )
    fixed = st.sampled_from(
        [np.zeros((4, 4)), np.diag([1, 1, 0, 1.0]), np.diag([-1, 1, 1, 1.0]), np.diag([1, 1, 1, 0.0])]
    )
    arbitrary = st.lists(st.floats(min_value=-3, max_value=3), min_size=16, max_size=16).map(
        lambda v: np.reshape(v, (4, 4))
    )
    return st.one_of(scale, shear, fixed, arbitrary)


@st.composite
def corruptions(draw, frame_count: int):
    """A function that corrupts a transforms document in place (one to three edits)."""
    edits = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["top", "frame", "drop", "element", "pose", "frames"]))
        index = draw(st.integers(0, frame_count - 1))
        if kind == "top":
            edits.append(("top", draw(st.sampled_from(CAMERA_FIELDS)), draw(values)))
        elif kind == "frame":
            edits.append(("frame", index, draw(st.sampled_from(FRAME_FIELDS)), draw(values)))
        elif kind == "drop":
            edits.append(
                (
                    "drop",
                    index,
                    draw(st.sampled_from(("file_path", "transform_matrix", "camera_angle_x", "fl_x", "frames"))),
                )
            )
        elif kind == "element":
            edits.append(("element", index, draw(st.integers(0, 3)), draw(st.integers(0, 3)), draw(scalars)))
        elif kind == "pose":
            edits.append(("pose", index, draw(pose_edits())))
        else:
            edits.append(("frames", draw(st.sampled_from([[], {}, None, "frames", [1, 2], [[]]]))))
    return edits


def corrupt(meta: dict, edits) -> dict:
    meta = copy.deepcopy(meta)
    frames = meta["frames"]
    for edit in edits:
        kind, rest = edit[0], edit[1:]
        if kind == "top":
            meta[rest[0]] = rest[1]
        elif kind == "frame":
            frames[rest[0]][rest[1]] = rest[2]
        elif kind == "drop":
            index, key = rest
            meta.pop(key, None) if key in ("frames", "camera_angle_x") else frames[index].pop(key, None)
        elif kind == "element":
            index, row, col, value = rest
            matrix = frames[index].get("transform_matrix")
            if (
                isinstance(matrix, list)
                and len(matrix) > row
                and isinstance(matrix[row], list)
                and len(matrix[row]) > col
            ):
                matrix[row][col] = value
        elif kind == "pose":
            index, edit_matrix = rest
            try:
                frames[index]["transform_matrix"] = (
                    np.array(frames[index]["transform_matrix"], dtype=float) @ edit_matrix
                ).tolist()
            except (TypeError, ValueError, KeyError, OverflowError):  # an earlier edit left no numeric matrix
                pass
        else:
            meta["frames"] = rest[0]
    return meta


def write_document(path: Path, meta: dict) -> None:
    path.write_text(json.dumps(meta))  # NaN and Infinity as Python's json writes them, which readers meet


RIGID = 1.01e-3  # the readers' documented tolerance on a pose (1e-3), and float32 rounding


def assert_rigid(c2w: torch.Tensor) -> None:
    """A rotation plus a translation, checked here: R^T R = I, det R = +1, last row (0, 0, 0, 1)."""
    R = c2w[:3, :3]
    assert (R.T @ R - torch.eye(3, dtype=R.dtype)).abs().max() <= RIGID, c2w
    assert abs(float(torch.linalg.det(R)) - 1.0) <= 3 * RIGID, c2w  # det R = +1: no mirror
    assert (c2w[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=c2w.dtype)).abs().max() <= RIGID, c2w


def check_scene(scene: Scene) -> None:
    """What a loaded scene promises training: finite rigid cameras with positive focal lengths, finite images in
    [0, 1] of one size per split, masks in [0, 1], finite bounds."""
    for split in (scene.train, scene.test):
        assert len({(v.width, v.height) for v in split}) <= 1
        for view in split:
            camera, image = view.camera, view.image
            assert torch.isfinite(camera.K).all() and camera.K[0, 0] > 0 and camera.K[1, 1] > 0, camera.K
            assert torch.isfinite(camera.viewmat).all()
            assert_rigid(camera.camtoworld.double())
            assert image.ndim == 3 and image.shape[-1] == 3 and (camera.height, camera.width) == tuple(image.shape[:2])
            assert torch.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
            if view.alpha is not None:
                assert view.alpha.shape == image.shape[:2] and view.alpha.min() >= 0 and view.alpha.max() <= 1
    assert torch.isfinite(scene.bounds).all()


def load_or_refuse(root: Path) -> Scene | None:
    """The property: a one-line MatsprayError naming a file of the dataset, or a usable Scene."""
    scene = read_or_refuse(lambda: load_scene(root, test_every=0), root)
    if scene is not None:
        check_scene(scene)
    return scene


@pytest.fixture(scope="module")
def blender_root():
    root = Path(tempfile.mkdtemp(prefix="fuzz-blender-"))
    return blender_folder(root)


@pytest.fixture(scope="module")
def nerfstudio_root():
    root = Path(tempfile.mkdtemp(prefix="fuzz-nerfstudio-"))
    return one_frame(root)


ORIGINALS: dict[Path, dict] = {}  # each fuzzed transforms file as first written, before any corruption


def corrupt_and_load(json_path: Path, edits) -> None:
    original = ORIGINALS.setdefault(json_path, json.loads(json_path.read_text()))
    write_document(json_path, corrupt(original, edits))
    load_or_refuse(json_path.parent)


@FUZZ
@given(edits=corruptions(frame_count=2))
def test_corrupted_blender_transforms(blender_root, edits):
    corrupt_and_load(blender_root / "transforms_train.json", edits)


@FUZZ
@given(edits=corruptions(frame_count=1))
def test_corrupted_nerfstudio_transforms(nerfstudio_root, edits):
    corrupt_and_load(nerfstudio_root / "transforms.json", edits)


@pytest.mark.parametrize("kind", ["blender", "nerfstudio"])
def test_the_unchanged_documents_load(kind, blender_root, nerfstudio_root):
    """The property's other side: with no edit, each document loads into a scene with every frame it lists, whose
    camera centres are the documents' own translations."""
    json_path = blender_root / "transforms_train.json" if kind == "blender" else nerfstudio_root / "transforms.json"
    original = ORIGINALS.setdefault(json_path, json.loads(json_path.read_text()))
    write_document(json_path, corrupt(original, []))
    scene = load_scene(json_path.parent, test_every=0)  # a refusal (MatsprayError) fails the test
    check_scene(scene)
    views = [*scene.train, *scene.test]
    assert len(views) == len(original["frames"]) > 0
    centres = sorted(tuple(np.round(view.camera.center.double().numpy(), 4)) for view in views)
    listed = sorted(tuple(np.round(np.array(frame["transform_matrix"])[:3, 3], 4)) for frame in original["frames"])
    assert centres == listed


def rigid_motions():
    """A 4x4 rotation about a random axis by a random angle, with a translation: a pose multiplied by it is a pose."""

    def motion(values) -> np.ndarray:
        axis, angle, shift = np.array(values[:3]), values[3], values[4:]
        axis = axis / np.linalg.norm(axis)
        cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        matrix = np.eye(4)  # Rodrigues' formula
        matrix[:3, :3] = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
        matrix[:3, 3] = shift
        return matrix

    unit = st.floats(min_value=0.1, max_value=1.0)
    return st.tuples(unit, unit, unit, st.floats(-np.pi, np.pi), *[st.floats(-2, 2)] * 3).map(motion)


def rigidity(pose: np.ndarray) -> tuple[float, float]:
    """(how far `pose` is from a rotation plus a translation, det of its 3x3 part), computed here with numpy: the
    largest entry of |R^T R - I| and of the last row's distance from (0, 0, 0, 1)."""
    R = pose[:3, :3]
    off = max(np.abs(R.T @ R - np.eye(3)).max(), np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max())
    return float(off), float(np.linalg.det(R))


@FUZZ
@pytest.mark.parametrize("kind", ["blender", "nerfstudio"])
@given(data=st.data())
def test_a_pose_loads_exactly_when_it_is_rigid(kind, blender_root, nerfstudio_root, data):
    """One frame's pose multiplied by a rigid motion, a scale, a shear, a mirror, a singular or an arbitrary matrix,
    the rest of the document unchanged: whether it must load is decided here (R^T R = I and det R = +1 within the
    readers' documented 1e-3, with a margin either side of that bound), not by the reader's own check. A rigid pose
    loads with the camera where the edited pose puts it; any other is refused, saying the pose is not rigid."""
    json_path = blender_root / "transforms_train.json" if kind == "blender" else nerfstudio_root / "transforms.json"
    original = ORIGINALS.setdefault(json_path, json.loads(json_path.read_text()))
    index = data.draw(st.integers(0, len(original["frames"]) - 1), label="frame")
    edit = data.draw(st.one_of(rigid_motions(), pose_edits()), label="edit")
    pose = np.array(original["frames"][index]["transform_matrix"], dtype=float) @ edit
    write_document(json_path, corrupt(original, [("pose", index, edit)]))
    off, det = rigidity(pose)
    if off <= 0.5e-3 and det > 0:
        scene = load_scene(json_path.parent, test_every=0)  # a refusal (MatsprayError) fails the test
        check_scene(scene)
        event("rigid: loaded")
        assert len(scene.train) == len(original["frames"]) and not scene.test  # the frames in the document's order
        centre = scene.train[index].camera.center.double().numpy()
        assert np.abs(centre - pose[:3, 3]).max() <= 1e-5, (centre, pose)  # float32 cameras
    elif off >= 2e-3 or det < 0:
        event("not rigid: refused")
        with pytest.raises(MatsprayError, match=r"'transform_matrix' is not a rigid camera pose") as refused:
            load_scene(json_path.parent, test_every=0)
        assert str(json_path) in str(refused.value)
    else:  # within a hair of the bound: either outcome, under the property's checks
        load_or_refuse(json_path.parent)
