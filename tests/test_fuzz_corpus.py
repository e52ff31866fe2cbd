"""The corruptions that fuzzing found unhandled, kept as fixed cases: each is refused by `matspray info` with
exit status 2 and one stderr line naming the file (and the frame and field), never a traceback or a run
that trains on it. The generated cases are in tests/test_fuzz_*.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from matspray.data import load_scene, write_image
from matspray.data.images import write_raw
from tests.test_captures import one_frame
from matspray.errors import DataError
from matspray.geometry.ply import read_ply, write_ply
from tests.test_ply import random_gaussians
from tests.test_readers import C2W_GL, FOCAL, H, W, blender_folder, write_colmap

ROOT = Path(__file__).resolve().parents[1]


def refusal(data: Path) -> str:
    """The one line `python -m matspray info data` prints when it refuses the dataset (exit status 2)."""
    done = subprocess.run([sys.executable, "-m", "matspray", "info", str(data)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert "Traceback" not in done.stderr
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    return lines[0]


def edit_frame(json_path: Path, index: int, **fields) -> None:
    meta = json.loads(json_path.read_text())
    meta["frames"][index].update(fields)
    json_path.write_text(json.dumps(meta))


def test_zero_transform_matrix(tmp_path):
    blender_folder(tmp_path)
    edit_frame(tmp_path / "transforms_train.json", 1, transform_matrix=np.zeros((4, 4)).tolist())
    line = refusal(tmp_path)
    assert "transforms_train.json: frame 1 ('train/r_001'): 'transform_matrix' is not a rigid camera pose" in line
    assert "last row" in line


def test_rotation_scaled_by_five(tmp_path):
    pose = np.array(C2W_GL, dtype=float)
    pose[:3, :3] *= 5.0
    blender_folder(tmp_path)
    edit_frame(tmp_path / "transforms_train.json", 0, transform_matrix=pose.tolist())
    line = refusal(tmp_path)
    assert "frame 0 ('train/r_000'): 'transform_matrix' is not a rigid camera pose: its rotation part is scaled" in line
    assert "column lengths 5, 5, 5" in line


def test_focal_length_as_a_word(tmp_path):
    one_frame(tmp_path, frame_extra={"fl_x": "fifty"})
    line = refusal(tmp_path)
    assert "transforms.json: frame 0 ('images/a.png'): 'fl_x' must be a number > 0, got \"fifty\"" in line


@pytest.mark.parametrize("focal", [0.0, -30.0])
def test_zero_or_negative_focal_length(tmp_path, focal):
    one_frame(tmp_path, meta_extra={"fl_x": focal})
    line = refusal(tmp_path)
    assert f"transforms.json: top-level 'fl_x' must be a number > 0, got {json.dumps(focal)}" in line


@pytest.mark.parametrize("angle", [0.0, -0.8])
def test_zero_or_negative_field_of_view(tmp_path, angle):
    blender_folder(tmp_path, meta_extra={"camera_angle_x": angle})
    line = refusal(tmp_path)
    assert "transforms_train.json: top-level 'camera_angle_x' must be an angle in radians between 0 and pi" in line


@pytest.mark.parametrize("bare", ["grey16", "rgb"])
def test_one_view_without_alpha_among_views_with_alpha(tmp_path, bare):
    blender_folder(tmp_path, frames=[{"file_path": f"train/r_00{i}", "transform_matrix": C2W_GL} for i in range(3)])
    image = tmp_path / "train" / "r_001.png"
    if bare == "grey16":
        write_raw(image, torch.rand(H, W), bits=16)
    else:
        write_image(image, torch.rand(H, W, 3))
    line = refusal(tmp_path)
    assert f"{image}: has no alpha channel or mask, but 2 of the 3 views in the train split have one (1 have none)" in line


def test_focal_length_as_a_numeric_string_is_read_as_the_number(tmp_path):
    """Repaired, not refused: nerfstudio's own float() reads "50.0", so exporters that write it work there."""
    blender_folder(tmp_path, meta_extra={"fl_x": str(FOCAL), "w": W, "h": H})
    scene = load_scene(tmp_path)
    assert float(scene.train[0].camera.K[0, 0]) == pytest.approx(FOCAL)


@pytest.mark.parametrize("name, edit, problem", [
    ("points3D.bin", lambda blob: blob[:-4], "ends inside the number of track entries of point 1"),  # pycolmap hung on it
    ("cameras.bin", lambda blob: (1 << 40).to_bytes(8, "little") + blob[8:], "says it holds 1099511627776 cameras"),
    ("cameras.bin", lambda blob: blob[:12] + (99).to_bytes(4, "little") + blob[16:], "camera 1 has the unknown camera model id 99"),
])
def test_damaged_colmap_binary_model(tmp_path, name, edit, problem):
    """pycolmap hangs or crashes on a truncated .bin file or a count past its end: refused before it reads them."""
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, n_images=2)
    path = tmp_path / "sparse" / "0" / name
    path.write_bytes(edit(path.read_bytes()))
    line = refusal(tmp_path)
    assert f"{path}: is not a valid COLMAP binary model: {problem}" in line


def test_zero_quaternion_in_a_ply(tmp_path):
    """A Gaussian with rot_0..3 all 0 has no rotation (3DGS divides by its length): refused, naming the row."""
    gaussians = random_gaussians(5, 1)
    gaussians.quats[3] = 0.0
    write_ply(tmp_path / "g.ply", gaussians)
    with pytest.raises(DataError, match=r"g\.ply: vertex row 3 has a zero quaternion \(rot_0\.\.3 all 0\).*set rot_0\.\.3 to 1 0 0 0"):
        read_ply(tmp_path / "g.ply")
