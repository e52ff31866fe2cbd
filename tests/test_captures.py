"""Real-capture layouts: nerfstudio / instant-ngp `transforms.json`, lens distortion, EXIF orientation."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from matspray.cli import main
from matspray.data import Camera, View, load_scene, undistort, write_image
from matspray.data.formats.nerfstudio import write_nerfstudio
from matspray.data.images import SCRATCH_PNG_LEVEL, linear_to_srgb, read_image
from matspray.data.undistort import Lens, cache_folder, distort_view, plan_undistortion
from matspray.errors import DataError
from tests.test_readers import write_colmap

pytest.importorskip("cv2")

W, H = 40, 30


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:  # sRGB values compared, as the project's metrics do
    mse = float(((linear_to_srgb(a) - linear_to_srgb(b)) ** 2).mean())
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def resample_pinhole(
    image: torch.Tensor, K_from: torch.Tensor, K_to: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """A pinhole image [H, W, C] (intrinsics K_from) as the same camera with intrinsics K_to would see it,
    by brute-force bilinear sampling; also where that sample lies inside the source [H, W] (bool)."""
    height, width = image.shape[:2]
    rows, cols = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    x = (cols - K_to[0, 2]) / K_to[0, 0] * K_from[0, 0] + K_from[0, 2]  # pixel in the source image
    y = (rows - K_to[1, 2]) / K_to[1, 1] * K_from[1, 1] + K_from[1, 2]
    grid = torch.stack([2 * x / width - 1, 2 * y / height - 1], dim=-1)[None].float()
    out = F.grid_sample(image.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    valid = (x >= 1) & (x <= width - 1) & (y >= 1) & (y <= height - 1)
    return out[0].permute(1, 2, 0), valid


def ring_views(count: int, width: int = W, height: int = H) -> list[View]:
    views = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        camera = Camera.look_at(
            [3 * math.cos(angle), 3 * math.sin(angle), 1.0], [0, 0, 0], [0, 0, 1], 0.8, width, height
        )
        camera.K[0, 2] += 0.25 * i  # per-view intrinsics that differ
        camera.K[0, 0] += i
        views.append(View(f"v{i:02d}", torch.rand(height, width, 3), None, camera))
    return views


# ------------------------------------------------------------------------------------------ the lens model
def test_lens_matches_opencv_projection():
    cv2 = pytest.importorskip("cv2")
    xy = np.random.default_rng(0).uniform(-0.5, 0.5, (20, 2))
    points = np.concatenate([xy, np.ones((20, 1))], axis=1)
    radtan = Lens(50, 52, 32.3, 24.1, 64, 48, (-0.2, 0.05, 0.001, -0.002, 0.01), model="OPENCV")
    fisheye = Lens(40, 41, 31.0, 25.0, 64, 48, (0.1, 0.02, -0.01, 0.003), fisheye=True, model="OPENCV_FISHEYE")
    for lens, project in ((radtan, cv2.projectPoints), (fisheye, cv2.fisheye.projectPoints)):
        K, D = lens.opencv()
        expected, _ = project(points[:, None, :], np.zeros(3), np.zeros(3), K, D)
        assert np.abs(lens.to_pixels(lens.distort(xy)) - 0.5 - expected.reshape(-1, 2)).max() < 1e-9
        assert np.abs(lens.undistort_pixels(lens.to_pixels(lens.distort(xy))) - xy).max() < 1e-8


# ------------------------------------------------------------------------------------------ nerfstudio
@pytest.fixture(scope="module")
def synth_object(tmp_path_factory):
    pytest.importorskip("mitsuba")
    from matspray.synth import SynthConfig, make_object

    out = tmp_path_factory.mktemp("synth")
    config = SynthConfig(
        shape="composite", seed=5, resolution=64, train_views=3, test_views=1, spp=64, texture_height=64, env_height=32
    )
    make_object(config, out, progress=False, notify=lambda _: None)
    return load_scene(out)


def test_distorted_nerfstudio_capture_undistorts_to_the_ground_truth(synth_object, tmp_path, capsys, monkeypatch):
    original = synth_object
    first = original.train[0].camera
    lens = Lens.from_K(first.K, first.width, first.height, (-0.12, 0.03, 0.002, -0.001, 0.0), model="OPENCV")
    distorted = {split: [distort_view(v, lens) for v in original.split(split)] for split in ("train", "test")}
    write_nerfstudio(tmp_path, distorted, lens=lens, separate_masks=True)
    written = sorted(p for p in tmp_path.rglob("*"))
    tmp_path.chmod(0o555)  # a read-only capture, as ../shared is in CI: nothing is written into it
    levels = []

    def write_recording_level(*args, png_level, **kwargs):
        levels.append(png_level)
        write_image(*args, png_level=png_level, **kwargs)

    monkeypatch.setattr(undistort, "write_image", write_recording_level)
    try:
        scene = load_scene(tmp_path)
    finally:
        tmp_path.chmod(0o755)
    assert sorted(p for p in tmp_path.rglob("*")) == written
    assert len(list(cache_folder(tmp_path).glob("*.png"))) == 4  # the undistorted views, in the cache ($MATSPRAY_CACHE)
    assert levels == [SCRATCH_PNG_LEVEL] * 4  # written fast: only this tool reads them back
    assert scene.format == "nerfstudio"
    assert [v.name for v in scene.train] == [v.name for v in original.train]
    assert [v.name for v in scene.test] == [v.name for v in original.test]
    plan = plan_undistortion(lens, "capture")
    scores = []
    for loaded, truth in zip(scene.views, original.views):
        assert torch.equal(loaded.camera.K, plan.K)
        assert (loaded.camera.viewmat - truth.camera.viewmat).abs().max() < 1e-5
        rgb, valid = resample_pinhole(truth.image, truth.camera.K, loaded.camera.K)
        alpha, _ = resample_pinhole(truth.alpha[..., None], truth.camera.K, loaded.camera.K)
        scores.append(psnr(loaded.image[valid], rgb[valid]))
        assert float((loaded.alpha - alpha[..., 0])[valid].abs().mean()) < 0.02
        assert valid.float().mean() > 0.8, float(valid.float().mean())
    assert min(scores) > 30.0
    # info says what it did, and a second load reads the cached images
    assert main(["info", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "format: nerfstudio" in printed and "undistorted OPENCV (k1=-0.12" in printed
    assert "0 made, 4 read from the cache" in printed
    with capsys.disabled():
        print(
            f"\nundistorted views against the undistorted ground truth ({lens.width}x{lens.height}): "
            f"PSNR {', '.join(f'{s:.1f}' for s in scores)} dB"
        )


def test_write_read_round_trip_with_per_frame_intrinsics(tmp_path):
    views = ring_views(5)
    write_nerfstudio(tmp_path, {"train": views[:3], "test": views[3:]})
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert "fl_x" not in meta and all("fl_x" in frame for frame in meta["frames"])
    scene = load_scene(tmp_path)
    assert [v.name for v in scene.train] == ["v00", "v01", "v02"] and [v.name for v in scene.test] == ["v03", "v04"]
    for loaded, original in zip(scene.views, views):
        assert torch.equal(loaded.camera.K, original.camera.K)
        assert (loaded.camera.viewmat - original.camera.viewmat).abs().max() < 1e-6
        assert (linear_to_srgb(loaded.image) - linear_to_srgb(original.image)).abs().max() <= 0.5 / 255 + 1e-6


def test_per_frame_intrinsics_project_where_computed_by_hand(tmp_path):
    write_image(tmp_path / "a.png", torch.rand(H, W, 3))
    write_image(tmp_path / "b.png", torch.rand(H, W, 3))
    c2w = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]  # at z = 4 looking down -z, y up
    frames = [
        {"file_path": "a", "transform_matrix": c2w, "fl_x": 50.0, "fl_y": 55.0, "cx": 21.0, "cy": 14.0},
        {"file_path": "b.png", "transform_matrix": c2w, "fl_x": 30.0, "cx": 19.0, "cy": 16.0},
    ]
    (tmp_path / "transforms.json").write_text(json.dumps({"w": W, "h": H, "frames": frames}))
    scene = load_scene(tmp_path, test_every=0)
    for view, (fx, fy, cx, cy) in zip(scene.train, [(50, 55, 21, 14), (30, 30, 19, 16)]):
        pixels, depth = view.camera.project(torch.tensor([[1.0, 1.0, 0.0]]))
        assert pixels[0].tolist() == pytest.approx([cx + fx / 4, cy - fy / 4], abs=1e-4)


def split_capture(root, count, extra):
    frames = []
    for i in range(count):
        write_image(root / "images" / f"f{i:02d}.png", torch.rand(8, 8, 3))
        frames.append({"file_path": f"images/f{i:02d}.png", "transform_matrix": np.eye(4).tolist()})
    frames.reverse()  # order in the file must not matter
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames, **extra}))
    return root


@pytest.mark.parametrize(
    "extra, train, test",
    [
        ({}, [1, 2, 3, 4, 5, 6, 7, 9], [0, 8]),  # every 8th held out, in file-path order
        ({"train_filenames": ["images/f01.png", "images/f02.png"], "test_filenames": ["images/f05.png"]}, [1, 2], [5]),
        ({"val_filenames": ["./images/f03"]}, [0, 1, 2, 4, 5, 6, 7, 8, 9], [3]),  # val serves as test; path forms vary
    ],
)
def test_split_lists(tmp_path, extra, train, test):
    scene = load_scene(split_capture(tmp_path, 10, extra))
    assert [v.name for v in scene.train] == [f"f{i:02d}" for i in train]
    assert [v.name for v in scene.test] == [f"f{i:02d}" for i in test]


def test_ignored_keys_are_noted(tmp_path, capsys):
    split_capture(tmp_path, 3, {"applied_transform": np.eye(4)[:3].tolist(), "aabb_scale": 16, "sharpness_cutoff": 1})
    assert main(["info", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "loading: ignored 'applied_transform'" in printed and "loading: ignored 'aabb_scale'" in printed
    assert "ignored unknown keys: sharpness_cutoff" in printed


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_exif_orientation_is_honoured(tmp_path, suffix):
    from PIL import Image

    upright = np.zeros((H, W, 3), dtype=np.uint8)  # wider than tall, a bright block at the top left
    upright[:10, :15] = 255
    upright[20:, 30:, 2] = 200
    stored = np.ascontiguousarray(np.rot90(upright, k=1))  # 40 x 30 on disk, turned a quarter to the left
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees clockwise to display"
    Image.fromarray(stored).save(tmp_path / f"photo{suffix}", exif=exif, quality=100)
    frame = {"file_path": f"photo{suffix}", "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 30.0, "w": W, "h": H, "frames": [frame]}))
    view = load_scene(tmp_path, test_every=0).train[0]
    assert (view.width, view.height) == (W, H)
    expected = torch.from_numpy(upright.astype(np.float32) / 255.0)
    assert float((linear_to_srgb(view.image) - expected).abs().mean()) < 0.01
    assert read_image(tmp_path / f"photo{suffix}")[0].shape[:2] == (W, H)  # without orient: as stored


# ------------------------------------------------------------------------------------------ COLMAP distortion
def analytic(xy: torch.Tensor) -> torch.Tensor:  # [..., 2] normalised pinhole coordinates -> [..., 3] smooth colours
    x, y = xy[..., 0], xy[..., 1]
    return torch.stack(
        [0.5 + 0.4 * torch.sin(4 * x) * torch.cos(3 * y), 0.5 + 0.4 * torch.cos(5 * y), 0.3 + 0.3 * x * x], -1
    )


def test_colmap_simple_radial_model_is_undistorted(tmp_path, capsys):
    pycolmap = pytest.importorskip("pycolmap")
    params = (36.0, 20.3, 14.8, -0.15)  # f, cx, cy, k
    poses = write_colmap(tmp_path, n_images=3, model="SIMPLE_RADIAL", params=params)
    lens = Lens(params[0], params[0], params[1], params[2], W, H, (params[3], 0.0, 0.0, 0.0), model="SIMPLE_RADIAL")
    grid = np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2)
    truth_xy = torch.from_numpy(lens.undistort_pixels(grid)).float().reshape(H, W, 2)  # what each photo pixel sees
    (tmp_path / "masks").mkdir()
    for i in range(3):
        write_image(tmp_path / "images" / f"img{i}.png", analytic(truth_xy))
        write_image(tmp_path / "masks" / f"img{i}.png", (truth_xy[..., 0] > 0).float()[..., None].expand(-1, -1, 3))
    scene = load_scene(tmp_path, test_every=0)
    view = scene.train[0]
    K = view.camera.K
    rows, cols = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    xy = torch.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1]], -1)
    score = psnr(view.image, analytic(xy))
    print(f"COLMAP SIMPLE_RADIAL undistorted against the analytic image: PSNR {score:.1f} dB")
    assert score > 35.0
    edge = xy[..., 0].abs() < 1.0 / float(K[0, 0])  # the mask's edge column may be blended
    assert torch.equal((view.alpha > 0.5)[~edge], (xy[..., 0] > 0)[~edge])
    # a 3D point lands on the undistorted pixel that samples where COLMAP projects it in the photo
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=list(params), camera_id=1)
    X = np.array([[0.3, -0.2, 0.4], [-0.5, 0.4, -0.2]])
    for view, (R, t) in zip(scene.train, poses):
        pixels, _ = view.camera.project(torch.tensor(X, dtype=torch.float32))
        xy_und = (pixels.double().numpy() - K[:2, 2].double().numpy()) / np.array([float(K[0, 0]), float(K[1, 1])])
        expected = camera.img_from_cam((X @ R.T + t))
        assert np.abs(lens.to_pixels(lens.distort(xy_und)) - expected).max() < 1e-3
    assert main(["info", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert (
        "loading: undistorted SIMPLE_RADIAL (k1=-0.15) to pinhole" in printed
        and "0 made, 3 read from the cache" in printed
    )
    write_image(tmp_path / "images" / "img1.png", analytic(truth_xy).flip(1))  # a changed photo is undistorted again
    # a load killed while writing to the cache left its temporary: the next load that writes removes it, and keeps
    # those of a process still writing
    cache = cache_folder(tmp_path)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    killed, writing = cache / f".img2-x.tmp-{gone.stdout.strip()}.png", cache / f".img0-x.tmp-{os.getpid()}.png"
    killed.write_bytes(b"half a PNG")
    writing.write_bytes(b"half a PNG")
    again = load_scene(tmp_path, test_every=0)
    assert not killed.exists() and writing.exists()
    writing.unlink()
    assert any("1 made, 2 read from the cache" in line for line in again.log)
    assert torch.equal(again.train[0].image, scene.train[0].image)
    assert (again.train[1].image - scene.train[1].image).abs().mean() > 0.05


# ------------------------------------------------------------------------------------------ bad input
def one_frame(root, frame_extra=None, meta_extra=None, image=True):
    if image:
        write_image(root / "images" / "a.png", torch.rand(H, W, 3))
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist(), **(frame_extra or {})}
    meta = {"fl_x": 30.0, "w": W, "h": H, "frames": [frame], **(meta_extra or {})}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize(
    "frame_extra, meta_extra, image, message",
    [
        ({}, {}, False, r"transforms.json: image 'images/a.png' of a frame does not exist"),
        (
            {"camera_model": "EQUIRECTANGULAR"},
            {},
            True,
            r"frame 0 \('images/a.png'\): unknown camera_model 'EQUIRECTANGULAR' \(known: PINHOLE, SIMPLE_PINHOLE, "
            r"OPENCV, OPENCV_FISHEYE\)",
        ),
        ({}, {"fl_x": None}, True, r"frame 0 \('images/a.png'\) has no intrinsics"),
        (
            {"camera_model": "OPENCV", "k1": -0.3, "fl_x": 12.0},
            {},
            True,
            r"images/a.png: the OPENCV \(k1=-0.3\) distortion is so strong that undistortion would keep only \d+%",
        ),
        ({"camera_model": "OPENCV", "k4": 0.1}, {}, True, r"camera_model OPENCV has no coefficient k4"),
        ({"mask_path": "masks/a.png"}, {}, True, r"its mask 'masks/a.png' does not exist"),
        (
            {},
            {"test_filenames": ["images/zzz.png"]},
            True,
            r"'test_filenames' names 'images/zzz.png', which is no frame's",
        ),
    ],
)
def test_bad_captures_are_named(tmp_path, frame_extra, meta_extra, image, message):
    one_frame(tmp_path, frame_extra, meta_extra, image)
    with pytest.raises(DataError, match=message):
        load_scene(tmp_path, test_every=0)


def test_undecodable_image_is_named(tmp_path):
    one_frame(tmp_path)
    (tmp_path / "images" / "a.png").write_bytes(b"not a picture")
    with pytest.raises(DataError, match=r"images/a.png: cannot read image"):
        load_scene(tmp_path, test_every=0)
    assert main(["info", str(tmp_path)]) == 2  # one line, no traceback


def test_strong_distortion_is_refused_with_the_fraction_kept():
    with pytest.raises(
        DataError,
        match=r"photo.jpg: the OPENCV \(k1=-0.2\) distortion is so strong that undistortion "
        r"would keep only 26% of the image",
    ):
        plan_undistortion(Lens(20, 20, 32, 24, 64, 48, (-0.2, 0.0, 0.0, 0.0), model="OPENCV"), "photo.jpg")


def test_unknown_colmap_camera_model_is_refused(tmp_path):
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, model="FOV", params=(45.0, 47.0, 19.5, 15.5, 0.1))
    with pytest.raises(
        DataError, match=r"camera model FOV, which MatSpray cannot undistort \(known: SIMPLE_PINHOLE, PINHOLE"
    ):
        load_scene(tmp_path)
