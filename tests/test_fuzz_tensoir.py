"""Property-based tests of the TensoIR reader: a valid `train_000/metadata.json` with fields replaced by values of
the wrong type, NaN/Inf, zero or negative (tests/test_fuzz_transforms.py: values), fields dropped, one number
of the comma-separated `cam_transform_mat` replaced, the pose scaled or sheared, or the JSON text truncated.

Either load_scene refuses with a one-line MatsprayError naming a file of the dataset, or it returns a usable
scene (tests/test_fuzz_transforms.py: check_scene).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.test_fuzz_transforms import FUZZ, load_or_refuse, pose_edits, scalars, values
from tests.test_readers import C2W_GL, FOV_X, H, W, write_rgba

FIELDS = ("cam_transform_mat", "cam_angle_x", "imw", "imh")
NUMBERS = st.sampled_from(["nan", "inf", "-inf", "0", "1e400", "abc", "", "1,2", " 3 ", "0x10", "1e-320"])


def intact_meta() -> dict:
    return {
        "cam_transform_mat": ",".join(str(float(v)) for row in C2W_GL for v in row),
        "cam_angle_x": FOV_X,
        "imw": W,
        "imh": H,
    }


@pytest.fixture(scope="module")
def root():
    root = Path(tempfile.mkdtemp(prefix="fuzz-tensoir-"))
    for split in ("train", "test"):
        folder = root / f"{split}_000"
        folder.mkdir()
        write_rgba(folder / "rgba.png")
        (folder / "metadata.json").write_text(json.dumps(intact_meta()))
    return root


@st.composite
def corruptions(draw):
    """The text of a corrupted metadata.json (one to three edits, then maybe truncated)."""
    meta = intact_meta()
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["field", "drop", "number", "pose", "list"]))
        key = draw(st.sampled_from(FIELDS))
        if kind == "field":
            meta[key] = draw(values)
        elif kind == "drop":
            meta.pop(key, None)
        elif kind == "number" and isinstance(meta.get("cam_transform_mat"), str):
            numbers = meta["cam_transform_mat"].split(",")
            numbers[draw(st.integers(0, len(numbers) - 1))] = draw(NUMBERS)
            meta["cam_transform_mat"] = ",".join(numbers)
        elif kind == "pose":
            matrix = np.array(C2W_GL, dtype=float) @ draw(pose_edits())
            meta["cam_transform_mat"] = ",".join(repr(float(v)) for v in matrix.flatten())
        elif kind == "list":  # the pose as a (nested) list, with one element replaced
            matrix = [list(map(float, row)) for row in C2W_GL]
            matrix[draw(st.integers(0, 3))][draw(st.integers(0, 3))] = draw(scalars)
            meta["cam_transform_mat"] = matrix if draw(st.booleans()) else sum(matrix, [])
    text = json.dumps(meta)  # NaN and Infinity as Python's json writes them
    return text[: draw(st.integers(0, len(text)))] if draw(st.booleans()) and draw(st.booleans()) else text


@FUZZ
@given(text=corruptions(), split=st.sampled_from(["train", "test"]))
def test_corrupted_tensoir_metadata(root, text, split):
    for folder in ("train_000", "test_000"):
        (root / folder / "metadata.json").write_text(json.dumps(intact_meta()))
    (root / f"{split}_000" / "metadata.json").write_text(text)
    load_or_refuse(root)
