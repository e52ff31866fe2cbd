"""Dataset readers: projections land where the layouts say, round trips are exact, bad input is named."""

import json
import math
import re

import numpy as np
import pytest
import torch

from matspray.data import Camera, View, load_scene, write_blender, write_image
from matspray.errors import DataError, SettingError

W, H = 40, 30
FOV_X = 0.8
FOCAL = 0.5 * W / math.tan(0.5 * FOV_X)

# camera at (0, 0, 4) looking down -z with y up: the identity rotation in Blender/OpenGL axes
C2W_GL = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]


def expected_pixel(point):
    """Where a world point lands for the camera above, worked out by hand in OpenGL axes."""
    x, y, z = point
    depth = 4.0 - z  # distance along the viewing direction (-z)
    return W / 2 + FOCAL * x / depth, H / 2 - FOCAL * y / depth  # image y grows downwards


def write_rgba(path, width=W, height=H):
    rgb = torch.rand(height, width, 3)
    alpha = torch.zeros(height, width)
    alpha[5:-5, 5:-5] = 1.0
    write_image(path, rgb, alpha)


def blender_folder(root, frames=None, meta_extra=None):
    (root / "train").mkdir(parents=True, exist_ok=True)
    if frames is None:
        frames = [
            {"file_path": "train/r_000", "transform_matrix": C2W_GL},
            {"file_path": "train/r_001", "transform_matrix": C2W_GL},
        ]
    for frame in frames:
        if "file_path" in frame and not (root / (frame["file_path"] + ".png")).exists():
            write_rgba(root / (frame["file_path"] + ".png"))
    meta = {"camera_angle_x": FOV_X, "frames": frames, **(meta_extra or {})}
    (root / "transforms_train.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize("point", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.3, -0.7, 1.0)])
def test_blender_projection_matches_hand_computation(tmp_path, point):
    scene = load_scene(blender_folder(tmp_path))
    pixels, depth = scene.train[0].camera.project(torch.tensor([point]))
    assert pixels[0].tolist() == pytest.approx(expected_pixel(point), abs=1e-4)
    assert float(depth[0]) == pytest.approx(4.0 - point[2], abs=1e-5)


def test_nerfstudio_intrinsics(tmp_path):
    meta = {"fl_x": 50.0, "fl_y": 55.0, "cx": 21.0, "cy": 14.0, "w": W, "h": H}
    root = blender_folder(tmp_path, meta_extra=meta)
    data = json.loads((root / "transforms_train.json").read_text())
    del data["camera_angle_x"]
    (root / "transforms_train.json").write_text(json.dumps(data))
    camera = load_scene(root).train[0].camera
    pixels, _ = camera.project(torch.tensor([[1.0, 1.0, 0.0]]))
    assert pixels[0].tolist() == pytest.approx([21.0 + 50.0 / 4, 14.0 - 55.0 / 4], abs=1e-4)


def test_tensoir_projection(tmp_path):
    for split in ("train", "test"):
        folder = tmp_path / f"{split}_000"
        folder.mkdir()
        write_rgba(folder / "rgba.png")
        matrix = ",".join(str(float(v)) for row in C2W_GL for v in row)
        meta = {"cam_transform_mat": matrix, "cam_angle_x": FOV_X, "imw": W, "imh": H}
        (folder / "metadata.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path)
    assert scene.format == "tensoir" and len(scene.train) == 1 and len(scene.test) == 1
    point = (0.5, 0.25, -1.0)
    pixels, _ = scene.test[0].camera.project(torch.tensor([point]))
    assert pixels[0].tolist() == pytest.approx(expected_pixel(point), abs=1e-4)


def write_colmap(root, n_images=3, model="PINHOLE", params=(45.0, 47.0, 19.5, 15.5)):
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model=model, width=W, height=H, params=list(params), camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    (root / "images").mkdir(parents=True)
    poses = []
    for i in range(n_images):
        angle = 0.3 * i
        R = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
        t = np.array([0.1 * i, -0.2, 5.0])
        pose = pycolmap.Rigid3d(np.concatenate([R, t[:, None]], axis=1))
        image = pycolmap.Image(name=f"img{i}.png", camera_id=1, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(image, pose)
        write_image(root / "images" / f"img{i}.png", torch.rand(H, W, 3))
        poses.append((R, t))
    reconstruction.add_point3D(np.array([0.1, 0.2, 0.3]), pycolmap.Track(), np.array([200, 100, 50], dtype=np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    reconstruction.write(str(root / "sparse" / "0"))
    return poses


def test_colmap_projection(tmp_path):
    poses = write_colmap(tmp_path, n_images=3)
    scene = load_scene(tmp_path, test_every=0)
    assert scene.format == "colmap" and len(scene.train) == 3
    X = np.array([0.3, -0.4, 0.5])
    for view, (R, t) in zip(scene.train, poses):
        cam = R @ X + t
        expected = (45.0 * cam[0] / cam[2] + 19.5, 47.0 * cam[1] / cam[2] + 15.5)
        pixels, _ = view.camera.project(torch.tensor([X], dtype=torch.float32))
        assert pixels[0].tolist() == pytest.approx(expected, abs=1e-3)
    assert scene.points.shape == (1, 3)


def test_colmap_without_images_is_refused(tmp_path):
    write_colmap(tmp_path, n_images=0)
    with pytest.raises(DataError, match="no registered images"):
        load_scene(tmp_path)


def test_blender_write_read_round_trip_is_exact(tmp_path):
    views = []
    for i in range(4):
        angle = 2 * math.pi * i / 4
        camera = Camera.look_at([3 * math.cos(angle), 3 * math.sin(angle), 1.2], [0, 0, 0], [0, 0, 1], 0.7, W, H)
        camera.K[0, 2] += 0.37 * i  # off-centre principal point must survive too
        views.append(View(f"r_{i:03d}", torch.rand(H, W, 3), torch.ones(H, W), camera))
    write_blender(tmp_path, {"train": views[:3], "test": views[3:]})
    scene = load_scene(tmp_path)
    for original, loaded in zip(views, scene.views):
        assert loaded.name == original.name
        assert torch.equal(loaded.camera.K, original.camera.K)
        assert (loaded.camera.viewmat - original.camera.viewmat).abs().max() < 1e-12
        assert (loaded.camera.width, loaded.camera.height) == (W, H)


def test_downscale_halves_images_and_intrinsics(tmp_path):
    scene = load_scene(blender_folder(tmp_path), downscale=2)
    view = scene.train[0]
    assert (view.width, view.height) == (W // 2, H // 2)
    assert float(view.camera.K[0, 0]) == pytest.approx(FOCAL / 2, rel=1e-6)


@pytest.mark.parametrize(
    "factor, message",
    [
        (float("nan"), "downscale: must be a finite number >= 1, got nan"),
        (float("inf"), "downscale: must be a finite number >= 1, got inf"),
        (0.5, "downscale: must be a finite number >= 1, got 0.5"),
        (1000, "downscale: 1000 shrinks r_000's 40x30 image to 1x1 px, under 8 px a side; use a smaller factor"),
    ],
)
def test_downscale_refuses_factors_that_leave_no_image(tmp_path, factor, message):
    with pytest.raises(SettingError, match=re.escape(message)):
        load_scene(blender_folder(tmp_path), downscale=factor)


def test_bounds_come_from_masks(tmp_path):
    views = []
    for i in range(6):
        angle = 2 * math.pi * i / 6
        camera = Camera.look_at([4 * math.cos(angle), 4 * math.sin(angle), 1.0], [0, 0, 0], [0, 0, 1], 0.7, 48, 48)
        yy, xx = torch.meshgrid(torch.arange(48) + 0.5, torch.arange(48) + 0.5, indexing="ij")
        centre, _ = camera.project(torch.zeros(1, 3))
        radius_px = float(camera.K[0, 0]) * 0.5 / 4  # a ball of radius 0.5 at distance 4
        alpha = (((xx - centre[0, 0]) ** 2 + (yy - centre[0, 1]) ** 2) < radius_px**2).float()
        views.append(View(f"r_{i:03d}", torch.rand(48, 48, 3), alpha, camera))
    write_blender(tmp_path, {"train": views})
    bounds = load_scene(tmp_path).bounds
    assert (bounds[0] < -0.4).all() and (bounds[1] > 0.4).all()
    assert (bounds[0] > -1.0).all() and (bounds[1] < 1.0).all()


# ------------------------------------------------------------------------------------------ bad input
def test_path_that_does_not_exist(tmp_path):
    with pytest.raises(DataError, match=r"missing: path does not exist"):
        load_scene(tmp_path / "missing")


def test_unknown_layout_lists_what_was_tried(tmp_path):
    with pytest.raises(DataError, match="no dataset layout recognised.*blender.*tensoir.*colmap") as refused:
        load_scene(tmp_path)
    assert "matspray colmap" not in str(refused.value)  # no photos: nothing to make a dataset of


@pytest.mark.parametrize("inside", ["", "images"])
def test_a_folder_of_photos_without_poses_is_pointed_to_structure_from_motion(tmp_path, inside):
    (tmp_path / inside).mkdir(exist_ok=True)
    for i in range(3):
        write_image(tmp_path / inside / f"IMG_000{i}.JPG", torch.rand(8, 8, 3))
    seen = f"{tmp_path}: holds 3 photos{' in images/' if inside else ''} but no camera poses, so it is not a dataset"
    hint = f"(`matspray colmap {tmp_path / inside} --out DATA` makes a dataset of them, then `matspray run"
    with pytest.raises(DataError) as refused:
        load_scene(tmp_path)
    assert str(refused.value).startswith(seen) and hint in str(refused.value)


def test_malformed_json(tmp_path):
    (tmp_path / "transforms_train.json").write_text('{"frames": [')
    with pytest.raises(DataError, match=r"transforms_train\.json: malformed JSON at line 1"):
        load_scene(tmp_path)


def test_frame_without_pose(tmp_path):
    blender_folder(tmp_path, frames=[{"file_path": "train/r_000"}])
    with pytest.raises(DataError, match="frame 0 has no 'transform_matrix'"):
        load_scene(tmp_path)


def test_missing_image_file(tmp_path):
    blender_folder(tmp_path)
    (tmp_path / "train" / "r_001.png").unlink()
    with pytest.raises(DataError, match="image 'train/r_001' of a frame does not exist"):
        load_scene(tmp_path)


def test_images_of_different_sizes_in_a_split(tmp_path):
    (tmp_path / "train").mkdir()
    write_rgba(tmp_path / "train" / "r_001.png", width=W + 2)
    blender_folder(tmp_path)
    with pytest.raises(DataError, match=r"r_001\.png: is 42x30 but 'r_000' in the train split is 40x30"):
        load_scene(tmp_path)


def test_views_are_brought_to_the_working_size_as_they_are_read(tmp_path, monkeypatch):
    """A dataset is never held whole at its photos' size: each view is shrunk before the next photo is read."""
    import matspray.data.formats.blender as blender
    from matspray.data import loader

    events = []
    read_image = blender.read_image
    monkeypatch.setattr(blender, "read_image", lambda *a, **k: events.append("read") or read_image(*a, **k))
    shrink = loader.WorkingSize.__call__
    monkeypatch.setattr(loader.WorkingSize, "__call__", lambda self, view: events.append("fit") or shrink(self, view))
    frames = [{"file_path": f"train/r_{i:03d}", "transform_matrix": C2W_GL} for i in range(3)]
    scene = load_scene(blender_folder(tmp_path, frames), downscale=None, max_size=W // 2)
    assert events == ["read", "fit"] * 3
    assert scene.downscale == 2.0
    assert all((v.width, v.height) == (W // 2, H // 2) for v in scene.train)
    assert float(scene.train[0].camera.K[0, 0]) == pytest.approx(FOCAL / 2, rel=1e-6)
    assert load_scene(tmp_path, downscale=None, max_size=4 * W).downscale == 1.0  # never enlarged
