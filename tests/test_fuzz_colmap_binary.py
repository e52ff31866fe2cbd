"""Property-based tests of the COLMAP reader on binary models (cameras.bin, images.bin, points3D.bin, and the
rigs.bin and frames.bin of COLMAP 3.12 and later, as pycolmap writes them): a field overwritten with a bad value
(a count, a camera model id, an id, a size, NaN or Inf), then the file truncated at any byte or bytes flipped.

pycolmap hangs or crashes on a truncated file or a count larger than the file, so read_colmap checks the
structure first (matspray.data.formats.colmap.check_binary_model). Either load_scene refuses with a one-line
MatsprayError naming a file of the dataset, or it returns a usable scene (tests/test_fuzz_transforms.py).
"""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from matspray.data import load_scene
from tests.fuzzing import damaged
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ, check_scene, load_or_refuse
from tests.test_readers import write_colmap

pytest.importorskip("pycolmap")

FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")
# 4- and 8-byte values a damaged or hand-edited model holds: NaN, Inf, zero, negative, huge counts, unknown model ids
VALUES = st.sampled_from(
    [
        struct.pack("<d", float("nan")),
        struct.pack("<d", float("inf")),
        struct.pack("<d", -1.0),
        struct.pack("<d", 0.0),
        struct.pack("<d", 1e300),
        struct.pack("<Q", 0),
        struct.pack("<Q", 2),
        struct.pack("<Q", 1 << 40),
        struct.pack("<q", -1),
        struct.pack("<i", 0),
        struct.pack("<i", -1),
        struct.pack("<i", 12),
        struct.pack("<i", 99),
        struct.pack("<i", 7),
        struct.pack("<i", 2),
        struct.pack("<f", float("nan")),
    ]
)


@pytest.fixture(scope="module")
def model():
    """(dataset folder, its binary files' intact contents)."""
    root = Path(tempfile.mkdtemp(prefix="fuzz-colmap-bin-"))
    write_colmap(root, n_images=3)
    return root, {path.name: path.read_bytes() for path in (root / "sparse" / "0").glob("*.bin")}


@st.composite
def corruptions(draw, intact: dict[str, bytes]):
    """(file name, its damaged bytes): one to three fields overwritten, then maybe truncated or flipped."""
    name = draw(st.sampled_from(FILES))
    blob = bytearray(intact[name])
    for _ in range(draw(st.integers(0, 3))):
        value = draw(VALUES)
        offset = draw(st.integers(0, max(0, (len(blob) - len(value)) // 4))) * 4
        blob[offset : offset + len(value)] = value
    cut, flips = draw(st.one_of(st.just((None, [])), damage(len(blob))))
    return name, damaged(bytes(blob), cut, flips)


def test_intact_binary_model_loads(model):
    root, intact = model
    scene = load_scene(root, test_every=0)
    check_scene(scene)
    assert len(scene.train) == 3 and scene.points.shape == (1, 3)


@settings(FUZZ, max_examples=400)
@given(data=st.data())
def test_corrupted_colmap_binary_model(model, data):
    root, intact = model
    folder = root / "sparse" / "0"
    for file_name, blob in intact.items():
        (folder / file_name).write_bytes(blob)
    name, blob = data.draw(corruptions(intact))
    (folder / name).write_bytes(blob)
    load_or_refuse(root)
