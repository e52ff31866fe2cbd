"""Property-based tests of environment-map reading: small lat-long maps written as .exr or .hdr by the project's
own writers, of any size (zero, not 2:1), 1 to 4 channels, holding NaN, Inf or negative values, then truncated at
any byte or with random bytes flipped, read by `EnvironmentMap.from_file` and `lights.load_envmap`.

Each reader refuses with a one-line MatsprayError naming the file, or returns a finite, non-negative [H, 2H, 3]
map; an intact 2:1 map of finite values comes back as written (negative radiance within a codec's ringing, at most
0.1 % of the map's energy, clamped to 0 by both readers, and more refused; HDR to its 8-bit mantissa).
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from matspray.data.images import write_raw
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import load_envmap
from tests.fuzzing import damaged, read_or_refuse
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ
from tests.test_light_ringing import brute_force_share

SPECIALS = st.sampled_from([float("nan"), float("inf"), -float("inf"), -1.0, -1e-3, 0.0, 1e30, 1e-30])
SIZES = st.integers(0, 10**13)  # what an HDR header's '-Y H +X W' line is edited to say


@st.composite
def maps(draw, suffix: str) -> np.ndarray:  # [H, W, C] float32
    rows = draw(st.integers(0, 4))
    cols = draw(st.one_of(st.just(2 * rows), st.just(2 * rows), st.integers(0, 9)))
    channels = draw(st.sampled_from([1, 2, 3, 4] if suffix == ".exr" else [1, 3]))  # RGBE stores 3
    values = np.random.default_rng(draw(st.integers(0, 2**16))).random((rows, cols, channels), dtype=np.float32) * 10
    for _ in range(draw(st.integers(0, 2)) if values.size else 0):  # RGBE holds no NaN or Inf: the writer's garbage
        values.flat[draw(st.integers(0, values.size - 1))] = draw(
            SPECIALS.filter(lambda v: suffix == ".exr" or abs(v) < 1e300)
        )
    return values


def write_map(path: Path, values: np.ndarray) -> None:
    if path.suffix == ".exr" and values.shape[-1] == 2:  # the project writes no 2-channel EXR; an exporter may
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"Y": values[..., 0].copy(), "A": values[..., 1].copy()}) as exr:
            exr.write(str(path))
    else:
        write_raw(path, torch.from_numpy(values))


def check_map(env: torch.Tensor) -> None:
    assert env.ndim == 3 and env.shape[0] >= 1 and env.shape[1] == 2 * env.shape[0] and env.shape[2] == 3, env.shape
    assert torch.isfinite(env).all() and env.min() >= 0


def expected(values: np.ndarray) -> torch.Tensor:  # what an intact file holds, as [H, W, 3]
    rgb = values[..., :1].repeat(3, -1) if values.shape[-1] < 3 else values[..., :3]
    return torch.from_numpy(rgb).clamp_min(0)


@pytest.fixture(scope="module")
def folder():
    return Path(tempfile.mkdtemp(prefix="fuzz-envmaps-"))


@FUZZ
@given(suffix=st.sampled_from([".exr", ".hdr"]), data=st.data())
def test_envmap_files(folder, suffix, data):
    values = data.draw(maps(suffix))
    path = folder / f"map{suffix}"
    path.unlink(missing_ok=True)
    try:
        write_map(path, values)
    except (ValueError, RuntimeError):  # OpenEXR writes no zero-size image: test an empty file instead
        assert values.size == 0
        path.write_bytes(b"")
    size = data.draw(st.one_of(st.none(), st.tuples(SIZES, SIZES))) if suffix == ".hdr" else None
    blob = path.read_bytes() if size is None else re.sub(rb"-Y \d+ \+X \d+", b"-Y %d +X %d" % size, path.read_bytes())
    cut, flips = data.draw(st.one_of(st.just((None, [])), damage(len(blob)))) if blob else (None, [])
    path.write_bytes(damaged(blob, cut, flips))
    env = read_or_refuse(lambda: load_envmap(str(path), height=None)[1], path, "load_envmap ")
    module = read_or_refuse(lambda: EnvironmentMap.from_file(path), path, "from_file ")
    for result in (env, None if module is None else module.map.detach()):
        if result is not None:
            check_map(result)
    rows, cols = values.shape[:2]
    intact = cut is None and not flips and size is None and rows >= 1 and cols == 2 * rows and values.shape[-1] != 2
    if intact and np.isfinite(values).all() and (suffix == ".exr" or values.max() < 1e30):
        rgb = torch.from_numpy(values[..., :1].repeat(3, -1) if values.shape[-1] < 3 else values[..., :3])
        if suffix == ".exr" and (rgb < 0).any() and brute_force_share(rgb.numpy()) > 1e-3:
            assert env is None and module is None, "a map of negative radiance is accepted"
            return
        assert env is not None and module is not None, "an intact map is refused"
        tolerance = 0 if suffix == ".exr" else expected(values).amax(-1, keepdim=True) / 128 + 1e-30
        assert ((env - expected(values)).abs() <= tolerance).all()
        assert ((module.map.detach() - env.clamp_min(1e-4)).abs() <= 1e-6 * env.clamp_min(1e-4)).all()
