"""Property-based tests of image reading: PNGs of 1 to 4 channels at 8 or 16 bits, then truncated at any byte or
with random bytes flipped, as the views of a Blender dataset.

An intact file is read back as written (greyscale promoted to RGB; alpha, when there is one, as the mask). A
corrupt one is refused with a one-line MatsprayError naming a file, or, where the damage leaves a decodable
image (a flipped pixel byte), gives a scene that training can use. A view without alpha among views with
alpha is refused (tests/test_fuzz_corpus.py).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from matspray.data.images import srgb_to_linear, write_raw
from tests.test_fuzz_transforms import FUZZ, load_or_refuse
from tests.test_readers import C2W_GL, FOV_X, H, W

formats = st.tuples(st.sampled_from([1, 2, 3, 4]), st.sampled_from([8, 16]))  # channels, bits


@st.composite
def damage(draw, size: int):
    """(cut, flips): keep the first `cut` bytes (None: all), then set bytes at offsets to values."""
    cut = draw(st.one_of(st.none(), st.integers(0, size - 1)))
    flips = draw(st.lists(st.tuples(st.integers(0, size - 1), st.integers(0, 255)), max_size=4))
    return cut, flips


def pixels(channels: int, seed: int) -> torch.Tensor:  # [H, W, C] stored values in [0, 1]
    values = torch.from_numpy(np.random.default_rng(seed).random((H, W, channels), dtype=np.float32))
    if channels in (2, 4):
        values[..., -1] = 0.0
        values[5:-5, 5:-5, -1] = 1.0  # a mask: the object in the middle
    return values


@pytest.fixture(scope="module")
def root():
    root = Path(tempfile.mkdtemp(prefix="fuzz-images-"))
    frames = [{"file_path": f"train/r_00{i}", "transform_matrix": C2W_GL} for i in range(2)]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": FOV_X, "frames": frames}))
    return root


def quantised(values: torch.Tensor, bits: int) -> torch.Tensor:
    top = 2**bits - 1
    return torch.round(values * top) / top


def check_read_as_written(view, values: torch.Tensor, bits: int) -> None:
    """Greyscale is promoted to RGB, sRGB decoded to linear; alpha is the last channel of 2 and 4."""
    stored = quantised(values, bits)
    colour = stored[..., :1].expand(-1, -1, 3) if values.shape[-1] in (1, 2) else stored[..., :3]
    assert torch.allclose(view.image, srgb_to_linear(colour), atol=1e-5)
    if values.shape[-1] in (2, 4):
        assert torch.equal(view.alpha, stored[..., -1])
    else:
        assert view.alpha is None


@FUZZ
@given(form=formats, seed=st.integers(0, 2**16), data=st.data())
def test_png_views(root, form, seed, data):
    channels, bits = form
    for i in range(2):  # both views in one format, so that alpha is all or nothing
        write_raw(root / "train" / f"r_00{i}.png", pixels(channels, seed + i), bits=bits)
    target = root / "train" / "r_001.png"
    blob = bytearray(target.read_bytes())
    cut, flips = data.draw(damage(len(blob)))
    for offset, value in flips:
        blob[offset] = value
    blob = blob[:cut] if cut is not None else blob
    target.write_bytes(bytes(blob))
    scene = load_or_refuse(root)
    if cut is None and not flips:  # an intact file is accepted and read as written
        assert scene is not None
        check_read_as_written(scene.train[0], pixels(channels, seed), bits)
        check_read_as_written(scene.train[1], pixels(channels, seed + 1), bits)
