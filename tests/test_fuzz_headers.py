"""Property-based tests of image headers that lie: a PNG (8 or 16 bit), JPEG, EXR or HDR whose header claims
another width and height (up to 60 000 x 60 000 and beyond, a decompression bomb's size) or, for a PNG, another
bit depth or colour type than its pixel data holds, read as `read_raw` and `image_size` read every photo and map.

Each is refused in one line naming the file (a claim beyond MAX_PIXELS says what the header claims), or, where the
header tells the truth, read as written. No reader allocates what a lying header claims (the test would run out of
memory)."""

from __future__ import annotations

import io
import re
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from matspray.data.images import MAX_PIXELS, image_size, read_raw, write_raw
from tests.fuzzing import read_or_refuse
from tests.test_fuzz_transforms import FUZZ

W, H = 12, 8
# what a header may claim: the truth, small lies, and sizes beyond the guard (60 000 x 60 000 is 3 600 megapixels)
SIDES = st.one_of(st.sampled_from([W, H]), st.integers(0, 64), st.sampled_from([60000, 2**31 - 1]))
SUFFIXES = (".png", ".jpg", ".exr", ".hdr")


def chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def with_png_header(blob: bytes, width: int, height: int, depth: int | None, colour: int | None) -> bytes:
    """The PNG with its IHDR rewritten (and its checksum fixed, so the lie is the header's, not damage)."""
    ihdr = bytearray(blob[16:29])
    ihdr[0:8] = struct.pack(">II", width, height)
    if depth is not None:
        ihdr[8] = depth
    if colour is not None:
        ihdr[9] = colour
    return blob[:8] + chunk(b"IHDR", bytes(ihdr)) + blob[33:]


def with_jpeg_size(blob: bytes, width: int, height: int) -> bytes:
    start = blob.find(b"\xff\xc0")  # baseline SOF0: length (2), precision (1), height (2), width (2)
    return blob[: start + 5] + struct.pack(">HH", min(height, 65535), min(width, 65535)) + blob[start + 9 :]


def with_exr_size(blob: bytes, width: int, height: int) -> bytes:
    start = blob.find(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    right, bottom = min(width - 1, 2**31 - 1), min(height - 1, 2**31 - 1)
    return blob[:start] + struct.pack("<iiii", 0, 0, right, bottom) + blob[start + 16 :]


def written(suffix: str, bits: int) -> tuple[bytes, torch.Tensor]:
    """An intact W x H file and the values it holds."""
    values = torch.from_numpy(np.random.default_rng(bits).random((H, W, 3), dtype=np.float32))
    if suffix == ".jpg":
        buffer = io.BytesIO()
        Image.fromarray((values.numpy() * 255).astype(np.uint8)).save(buffer, "JPEG")
        return buffer.getvalue(), values
    path = Path(tempfile.mkdtemp(prefix="fuzz-headers-")) / f"intact{suffix}"
    write_raw(path, values, bits=bits)
    return path.read_bytes(), values


@pytest.fixture(scope="module")
def folder():
    return Path(tempfile.mkdtemp(prefix="fuzz-headers-"))


@settings(FUZZ, max_examples=120)
@given(
    suffix=st.sampled_from(SUFFIXES),
    bits=st.sampled_from([8, 16]),
    width=SIDES,
    height=SIDES,
    depth=st.one_of(st.none(), st.sampled_from([1, 2, 4, 7, 8, 16, 32])),
    colour=st.one_of(st.none(), st.sampled_from([0, 1, 2, 3, 4, 5, 6, 7])),
)
def test_image_headers_that_lie_about_size_or_depth(folder, suffix, bits, width, height, depth, colour):
    blob, values = written(suffix, bits if suffix == ".png" else 8)
    if suffix == ".png":
        blob = with_png_header(blob, width, height, depth, colour)
    elif suffix == ".jpg":
        blob = with_jpeg_size(blob, width, height)
    elif suffix == ".exr":
        blob = with_exr_size(blob, max(width, 1), max(height, 1))
    else:
        blob = re.sub(rb"-Y \d+ \+X \d+", b"-Y %d +X %d" % (height, width), blob)
    path = folder / f"photo{suffix}"
    path.write_bytes(blob)
    pixels = read_or_refuse(lambda: read_raw(path), path, f"{suffix} read ")
    size = read_or_refuse(lambda: image_size(path), path, f"{suffix} size ")
    stored = {".jpg": 65535, ".exr": 2**31}.get(suffix, 2**32)  # the largest side the header can hold
    claimed = min(max(width, suffix == ".exr"), stored) * min(max(height, suffix == ".exr"), stored)
    if claimed > MAX_PIXELS:
        assert pixels is None and size is None, "a header claiming a decompression bomb's size was read"
        if depth is None and colour is None:  # else the header may be refused for its depth first
            with pytest.raises(Exception, match=rf"^{re.escape(str(path))}: its header claims \d+x\d+ pixels"):
                read_raw(path)
        return
    if pixels is not None:
        assert pixels.ndim == 3 and torch.isfinite(pixels).all()
    truthful = (width, height) == (W, H) and depth in (None, bits) and colour in (None, 2)
    if truthful and suffix != ".jpg":
        assert pixels is not None and size == (W, H), "an intact image is refused"
        tolerance = 1 / 255 if suffix == ".png" and bits == 8 else 1 / 128 if suffix == ".hdr" else 1e-4
        assert (pixels[..., :3] - values).abs().max() <= tolerance


def test_a_60000_pixel_square_photo_is_one_line_naming_it(tmp_path):
    """a JPEG whose header claims 60 000 x 60 000 pixels ended in Pillow's DecompressionBombError."""
    from matspray.errors import DataError

    blob, _ = written(".jpg", 8)
    path = tmp_path / "IMG_0001.jpg"
    path.write_bytes(with_jpeg_size(blob, 60000, 60000))
    for read in (read_raw, image_size):
        with pytest.raises(DataError) as caught:
            read(path)
        assert str(caught.value) == (
            f"{path}: its header claims 60000x60000 pixels (3600 megapixels), more than the 179 megapixels an image "
            "may have (the file is damaged, or too large to read: shrink it)"
        )
