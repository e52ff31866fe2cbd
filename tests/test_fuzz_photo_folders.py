"""Property-based tests of the photo folders `matspray colmap` reads: zero to five files of any kind (photos as PNG or
JPEG in grey, grey + alpha, RGB, RGBA, palette, 1-bit, 16-bit grey or CMYK, of mixed and tiny sizes, EXIF-rotated;
the same truncated or with bytes flipped; garbage, text or another format behind a .jpg or .png suffix), named with
spaces, Unicode, upper-case suffixes or bytes that are no UTF-8, beside hidden files, a subfolder of photos and
sometimes a text file, with or without a folder of masks (one missing, damaged or of another size).

The folder is checked as `run_sfm` checks it before structure from motion starts (`list_photos`, then
`prepare_photos`): either a one-line MatsprayError naming the folder, a photo or a mask, or every photo prepared as
an 8-bit grey or RGB image no larger than `max_size`, upright, as bright as the photo (16-bit ones scaled, not
clipped), one size when one camera is asked for. A few refused folders go through `python -m matspray colmap`
itself: exit status 2, one stderr line, no traceback, and pycolmap never starts.
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from PIL import Image

from matspray.data.sfm import MIN_PHOTO_SIDE, SfmConfig, list_photos, prepare_photos, run_sfm
from matspray.errors import MatsprayError
from tests.conftest import run_cli
from tests.fuzzing import damaged
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ

ROOT = Path(__file__).resolve().parents[1]
MODES = ["RGB", "L", "I;16", "RGBA", "LA", "P", "1", "CMYK"]
# hypothesis draws the first entries of a list most: the usual ones come first, the rare ones last
SIDES = [64, 40, 97, MIN_PHOTO_SIDE]
TINY = [1, 2, MIN_PHOTO_SIDE - 1]
STEMS = ["p{}", "photo {}", "фото {}", "写真{}", "IMG_{}.final", "P{}"]
NOT_UTF8 = os.fsdecode(b"bad\xff")  # a name a Latin-1 system wrote: no UTF-8


def pixels(mode: str, width: int, height: int, seed: int) -> tuple[Image.Image, np.ndarray | None]:
    """A photo in `mode` and the brightness [H, W, C] in [0, 1] it shows (None where no simple truth: CMYK, palette)."""
    rng = np.random.default_rng(seed)
    values = rng.uniform(0.2, 0.8, size=(height, width, 3))
    grey = values.mean(-1, keepdims=True)
    if mode == "I;16":
        return Image.fromarray(np.round(grey[..., 0] * 65535).astype(np.uint16)), grey
    if mode in ("L", "LA", "1"):
        image = Image.fromarray(np.round(grey[..., 0] * 255).astype(np.uint8))
        return (image.convert("LA") if mode == "LA" else image.convert("1") if mode == "1" else image), grey
    image = Image.fromarray(np.round(values * 255).astype(np.uint8))
    if mode in ("RGBA", "P", "CMYK"):
        image = image.convert(mode)
    return image, None if mode in ("P", "CMYK") else values


DEFECTS = ["damaged", "garbage", "other format", "tiny", "not UTF-8"]


@st.composite
def photo_files(draw, index: int, defect: str | None):
    """(file name, bytes, what the prepared photo must look like: (upright width, height, brightness) or None)."""
    stem = draw(st.sampled_from(STEMS)).format(index)
    mode = draw(st.sampled_from(MODES))
    jpeg = mode == "CMYK" or mode in ("L", "RGB") and draw(st.booleans())
    width, height = draw(st.sampled_from(SIDES)), draw(st.sampled_from(SIDES))
    if defect == "tiny":
        width = draw(st.sampled_from(TINY))
    image, truth = pixels(mode, width, height, draw(st.integers(0, 2**16)))
    buffer = io.BytesIO()
    orientation = draw(st.sampled_from([None, 1, 3, 6, 8])) if jpeg else None
    if jpeg:
        exif = Image.Exif()
        if orientation is not None:
            exif[0x0112] = orientation
        image.save(buffer, format="JPEG", quality=95, exif=exif.tobytes())
    else:
        image.save(buffer, format="PNG")
    blob = buffer.getvalue()
    suffix = draw(st.sampled_from([".jpg", ".JPG", ".jpeg"] if jpeg else [".png", ".PNG"]))
    upright = (height, width) if orientation in (6, 8) else (width, height)
    expected = (*upright, truth)
    if defect == "damaged":
        cut, flips = draw(damage(len(blob)))
        blob, expected = damaged(blob, cut, flips), None
    elif defect == "garbage":
        blob, expected = (
            draw(
                st.sampled_from(
                    [b"", b"\0" * 64, b"not a photo\n", b"\xff\xd8\xff\xe0", b"\x89PNG\r\n\x1a\n", bytes(range(256))]
                )
            ),
            None,
        )
    elif defect == "other format":  # decodable, but GIF, BMP, TIFF or WebP behind a .jpg or .png suffix
        other = io.BytesIO()
        Image.new("RGB", (width, height), (90, 120, 150)).save(
            other, format=draw(st.sampled_from(["GIF", "BMP", "TIFF", "WEBP"]))
        )
        blob, expected = other.getvalue(), (width, height, np.full((1, 1, 3), [90 / 255, 120 / 255, 150 / 255]))
        suffix = draw(st.sampled_from([".jpg", ".png"]))
    elif defect == "not UTF-8":
        stem = NOT_UTF8
    return stem + suffix, blob, expected


@st.composite
def folders(draw):
    """(files: [(name, bytes, expected)], extras: what else lies in the folder, masks: None or {photo name: mask kind}).
    Most photos are sound, so that a folder often gets through to the checks of its other photos: 0 to 2 defects."""
    count = draw(st.sampled_from([3, 4, 5, 3, 4, 5, 2, 1, 0]))
    defects = (
        {
            draw(st.integers(0, count - 1)): draw(st.sampled_from(DEFECTS))
            for _ in range(draw(st.sampled_from([0, 1, 0, 1, 2])))
        }
        if count
        else {}
    )
    files = [draw(photo_files(i, defects.get(i))) for i in range(count)]
    extras = draw(
        st.lists(
            st.sampled_from(["hidden", "subfolder", "folder named like a photo"] * 3 + ["text"]),
            unique=True,
            max_size=2,
        )
    )
    masks = None
    if draw(st.sampled_from([False, False, True])):
        masks = {
            name: draw(st.sampled_from(["good", "good", "good", "good", "missing", "garbage", "other size"]))
            for name, _, _ in files
        }
    return files, extras, masks


def write_folder(root: Path, files, extras, masks) -> tuple[Path, Path | None]:
    shutil.rmtree(root, ignore_errors=True)
    folder = root / "photos"
    folder.mkdir(parents=True)
    for name, blob, _ in files:
        (folder / name).write_bytes(blob)
    for extra in extras:
        if extra == "hidden":
            (folder / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
        elif extra == "subfolder":  # photos in a subfolder are not read
            (folder / "more").mkdir()
            Image.new("RGB", (64, 48)).save(folder / "more" / "extra.jpg")
        elif extra == "text":
            (folder / "notes.txt").write_text("taken on a cloudy day")
        else:
            (folder / "thumbs.jpg").mkdir()
    mask_dir = None
    if masks is not None:
        mask_dir = root / "masks"
        mask_dir.mkdir()
        for name, blob, expected in files:
            kind, stem = masks[name], Path(name).stem
            if kind == "missing":
                continue
            if kind == "garbage":
                (mask_dir / f"{stem}.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
                continue
            width, height = expected[:2] if expected is not None else (40, 40)
            if kind == "other size":
                width, height = width + 7, height * 2
            Image.new("L", (width, height), 255).save(mask_dir / f"{stem}.png")
    return folder, mask_dir


def prepare(root: Path, folder: Path, config: SfmConfig, mask_dir: Path | None):
    out = root / "prepared"
    out.mkdir()
    mask_out = None
    if mask_dir is not None:
        mask_out = root / "prepared-masks"
        mask_out.mkdir()
    photos = list_photos(folder)
    return photos, out, prepare_photos(photos, out, config, mask_dir, mask_out), mask_out


def check_prepared(files, photos, out: Path, sizes: dict, config: SfmConfig, mask_out: Path | None) -> None:
    expected = {name: e for name, _, e in files}
    assert len(photos) >= 3 and [p.name for p in photos] == sorted(p.name for p in photos)
    assert all(p.parent.name == "photos" for p in photos)  # nothing from the subfolder
    for photo in photos:
        with Image.open(out / photo.name) as prepared:
            prepared.load()
            assert prepared.mode in ("L", "RGB") and prepared.format in ("JPEG", "MPO", "PNG"), (
                prepared.mode,
                prepared.format,
            )
            assert (
                prepared.size == sizes[photo.name] and max(prepared.size) <= config.max_size and min(prepared.size) >= 1
            )
            shown = np.asarray(prepared.convert("RGB"), dtype=np.float64) / 255.0
        truth = expected.get(photo.name)
        if truth is not None:
            width, height, brightness = truth
            assert min(width, height) >= MIN_PHOTO_SIDE, "a tiny photo was accepted"
            scale = min(1.0, config.max_size / max(width, height))
            assert abs(prepared.size[0] - width * scale) <= 1 and abs(prepared.size[1] - height * scale) <= 1, (
                prepared.size,
                truth[:2],
            )
            if brightness is not None:  # as bright as the photo: 16-bit values scaled, alpha dropped
                assert abs(shown.mean() - brightness.mean()) < 0.06, (photo.name, shown.mean(), brightness.mean())
        if mask_out is not None:
            with Image.open(mask_out / f"{photo.name}.png") as mask:
                assert mask.size == prepared.size
    if config.single_camera:
        assert len(set(sizes.values())) == 1


@pytest.fixture(scope="module")
def root():
    return Path(tempfile.mkdtemp(prefix="fuzz-photos-"))


@settings(FUZZ, max_examples=200)
@given(folder=folders(), single_camera=st.booleans(), max_size=st.sampled_from([64, 100, 1600]))
def test_photo_folders(root, folder, single_camera, max_size):
    files, extras, masks = folder
    photos_dir, mask_dir = write_folder(root / "case", files, extras, masks)
    config = SfmConfig(single_camera=single_camera, max_size=max_size)
    try:
        photos, out, sizes, mask_out = prepare(root / "case", photos_dir, config, mask_dir)
    except MatsprayError as exc:
        message = str(exc)
        assert "\n" not in message, message
        assert str(photos_dir) in message or (mask_dir is not None and str(mask_dir) in message), message
        event(f"refused: {message.split(': ', 1)[-1][:24]}")
        return
    event("accepted")
    check_prepared(files, photos, out, sizes, config, mask_out)


# ------------------------------------------------------------------------------------------ the command
def good_photos(folder: Path, count: int = 3) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        pixels("RGB", 64, 48, i)[0].save(folder / f"p{i}.jpg", quality=95)


def refused_folders(tmp_path: Path):
    empty = tmp_path / "empty"
    empty.mkdir()
    tiny = tmp_path / "tiny"
    good_photos(tiny)
    Image.new("RGB", (2, 2)).save(tiny / "thumb.png")
    truncated = tmp_path / "truncated"
    good_photos(truncated)
    blob = (truncated / "p1.jpg").read_bytes()
    (truncated / "p1.jpg").write_bytes(blob[: len(blob) // 2])
    return [(empty, "has 0 photos"), (tiny / "thumb.png", "is 2x2 pixels"), (truncated / "p1.jpg", "cannot read image")]


def test_colmap_refuses_bad_folders_in_one_line(tmp_path):
    """`python -m matspray colmap` on an empty folder and on one with a truncated JPEG: exit 2, one line,
    no traceback."""
    pytest.importorskip("pycolmap")
    for named, problem in refused_folders(tmp_path)[::2]:
        folder = named if named.is_dir() else named.parent
        out = tmp_path / f"{folder.name}-dataset"
        done = run_cli("colmap", folder, "--out", out, "--quiet", cwd=ROOT)
        assert "Traceback" not in done.stderr and done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"matspray colmap: error: {named}: {problem}"), done.stderr
        assert not out.exists() and not list(tmp_path.glob(f".{out.name}.tmp-*"))


def test_bad_folders_are_refused_before_structure_from_motion(tmp_path, monkeypatch):
    """run_sfm on the empty folder, the one with a 2x2 photo and the one with a truncated JPEG: refused,
    pycolmap not started."""
    pycolmap = pytest.importorskip("pycolmap")

    def started(*args, **kwargs):
        raise AssertionError("structure from motion started on a folder that is refused")

    monkeypatch.setattr(pycolmap, "extract_features", started)
    for named, problem in refused_folders(tmp_path):
        folder = named if named.is_dir() else named.parent
        with pytest.raises(MatsprayError, match=problem):
            run_sfm(folder, tmp_path / f"{folder.name}-dataset", progress=False, log=lambda _: None)
