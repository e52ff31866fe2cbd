"""`matspray colmap`: structure from motion on a folder of photos, and the photo folders it refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from matspray.cli import main
from matspray.data import load_scene, write_image
from matspray.data.sfm import SfmConfig, prepare_photo, run_sfm
from matspray.errors import ConfigError, DataError

pytest.importorskip("pycolmap")
pytest.importorskip("cv2")

SCEAUX = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "captures" / "sceaux" / "images"


def photos(folder: Path, count: int, size=(48, 64), suffix=".png") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        write_image(folder / f"p{i}{suffix}", torch.rand(*size, 3))
    return folder


@pytest.mark.slow
def test_four_real_photos_register_and_load(tmp_path):
    if not SCEAUX.is_dir():
        pytest.skip(f"shared data not found at {SCEAUX}")
    subset, masks = tmp_path / "photos", tmp_path / "masks"
    subset.mkdir()
    for name in sorted(p.name for p in SCEAUX.iterdir())[:4]:
        (subset / name).write_bytes((SCEAUX / name).read_bytes())
        mask = torch.zeros(769, 1024)  # full size: resized with its photo
        mask[200:600, 300:800] = 1.0
        write_image(masks / f"{Path(name).stem}.png", mask[..., None].expand(-1, -1, 3))
    out = tmp_path / "dataset"
    result = run_sfm(
        subset, out, SfmConfig(max_size=400, single_camera=True), masks=masks, progress=False, log=lambda _: None
    )
    assert result.registered == 4 and result.model_sizes == [4]
    assert result.mean_reprojection_error < 1.5
    assert not list(tmp_path.glob(".dataset.tmp-*"))  # the work folder was renamed, nothing left behind
    true_focal = 1050.7137 * 400 / 1024  # K.txt, at the size given to SfM
    assert abs(result.focal / true_focal - 1) < 0.15, result.focal
    scene = load_scene(out)
    assert (
        scene.format == "colmap"
        and len(scene.views) == 4
        and (scene.views[0].width, scene.views[0].height) == (400, 300)
    )
    assert any("undistorted images: 0 made, 4 read from the cache" in line for line in scene.log)
    coverage = float(scene.views[0].alpha.mean())  # the box covers 400 x 500 of 769 x 1024 before undistortion
    assert abs(coverage - 400 * 500 / (769 * 1024)) < 0.03, coverage


def test_photos_that_do_not_match_are_explained(tmp_path, capsys):
    photos(tmp_path / "noise", 3, size=(64, 64))
    code = main(["colmap", str(tmp_path / "noise"), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 2
    error = capsys.readouterr().err
    assert "only 0 of 3 photos could be registered (at least 3 needed)" in error and "more overlap" in error
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.tmp-*"))


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: photos(d, 2), r"has 2 photos; structure from motion needs at least 3"),
        (
            lambda d: (photos(d, 3), (d / "p9.heic").write_bytes(b"x")),
            r"p9.heic: is not a JPEG or PNG photo \('.heic'\)",
        ),
        (lambda d: (photos(d, 3), (d / "p1.png").write_bytes(b"broken")), r"p1.png: cannot read image"),
        (
            lambda d: (photos(d, 2), write_image(d / "z.png", torch.rand(30, 64, 3))),
            r"z.png: is 64x30 but p0.png is 64x48 \(one camera for every photo needs photos of one size\)",
        ),
    ],
)
def test_bad_photo_folders_are_named(tmp_path, make, message):
    folder = tmp_path / "photos"
    folder.mkdir()
    make(folder)
    with pytest.raises(DataError, match=message):
        run_sfm(folder, tmp_path / "out", SfmConfig(single_camera=True), progress=False, log=lambda _: None)
    assert not (tmp_path / "out").exists()


def test_missing_mask_and_bad_settings(tmp_path):
    folder = photos(tmp_path / "photos", 3)
    (tmp_path / "masks").mkdir()
    write_image(tmp_path / "masks" / "p0.png", torch.ones(48, 64, 3))
    with pytest.raises(DataError, match=r"masks: has no mask for photo 'p1.png'"):
        run_sfm(folder, tmp_path / "out", masks=tmp_path / "masks", progress=False, log=lambda _: None)
    with pytest.raises(ConfigError, match="matcher must be one of exhaustive, sequential"):
        run_sfm(folder, tmp_path / "out", SfmConfig(matcher="vocab"), progress=False)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(DataError, match="full: already exists and is not empty"):
        run_sfm(folder, tmp_path / "full", progress=False)


def test_exif_rotated_photo_is_written_upright(tmp_path):
    from PIL import Image

    stored = (np.random.default_rng(0).random((40, 30, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(tmp_path / "a.jpg", exif=exif, quality=95)
    (tmp_path / "out").mkdir()
    assert prepare_photo(tmp_path / "a.jpg", tmp_path / "out", 1600, None, None) == (40, 30)
    with Image.open(tmp_path / "out" / "a.jpg") as written:
        assert written.size == (40, 30) and written.getexif().get(0x0112, 1) == 1


@pytest.mark.parametrize("max_size", [1600, 40])
def test_a_resized_photo_gets_the_focal_plane_resolution_of_its_pixels(tmp_path, max_size):
    """pycolmap's focal prior comes from the focal plane resolution; a photo shrunk (before, or here) must say so."""
    from PIL import Image

    exif = Image.Exif()
    inner = exif.get_ifd(0x8769)
    inner.update({0xA002: 4000, 0xA003: 3000, 0xA20E: 1000.0, 0xA20F: 1000.0, 0xA210: 2, 0x920A: 50.0})
    Image.fromarray(np.zeros((60, 80, 3), np.uint8)).save(tmp_path / "a.jpg", exif=exif.tobytes(), quality=95)
    (tmp_path / "out").mkdir()
    width, height = prepare_photo(tmp_path / "a.jpg", tmp_path / "out", max_size, None, None)
    with Image.open(tmp_path / "out" / "a.jpg") as written:
        kept = written.getexif().get_ifd(0x8769)
    assert (kept[0xA002], kept[0xA003]) == (width, height) == ((80, 60) if max_size > 80 else (40, 30))
    assert kept[0xA20E] == pytest.approx(1000.0 * width / 4000) and kept[0x920A] == 50.0


def test_features_are_extracted_in_batches_of_24_photos_and_a_single_camera_is_shared(monkeypatch, tmp_path):
    import pycolmap

    from matspray.data.sfm import extract_sift

    calls = []

    def record(database, image_dir, image_names, camera_mode, reader_options, extraction_options, device):
        calls.append((list(image_names), reader_options.existing_camera_id, extraction_options.num_threads))

    monkeypatch.setattr(pycolmap, "extract_features", record)
    names = [f"{i:05d}.png" for i in range(50)]
    extract_sift(tmp_path / "db", tmp_path, names, "PINHOLE", pycolmap.CameraMode.SINGLE, 2, 0.004, progress=False)
    assert [len(batch) for batch, _, _ in calls] == [24, 24, 2]
    assert [name for batch, _, _ in calls for name in batch] == names  # every photo once, in order
    assert [camera for _, camera, _ in calls][1:] == [1, 1]  # the later batches share the first one's camera
    assert {threads for _, _, threads in calls} == {2}
