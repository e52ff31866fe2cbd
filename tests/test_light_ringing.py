"""Lights as HDRI libraries ship them: a lossy EXR codec (DWAB) rings a little below zero next to dark pixels, in a
night map as deep as in a day map. Such a map loads with one notice line (file, count, share of the energy) and the
ringing clamped to 0; a map whose negative values hold a meaningful share of its energy (> 0.1 %) is refused in one
line naming the file. Every HDRI of ../shared/data/hdri and of the package loads with at most one notice line."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch

import matspray.render.shade.lights as lights
from matspray.data.images import read_raw, write_raw
from matspray.errors import DataError
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import NEGATIVE_ENERGY_SHARE, load_envmap, negative_energy

SHARED_HDRI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "hdri"


@pytest.fixture(autouse=True)
def fresh_notices(monkeypatch):
    monkeypatch.setattr(lights, "_NOTICED", set())  # each test hears its own notices


def panorama(rows: int, kind: str, seed: int = 0) -> np.ndarray:  # [rows, 2 rows, 3] float32 linear radiance
    """A night map as the held-out one (a black ground, a sky of a ten-thousandth, a moon of 11 600 and a few
    street lamps: mean ~0.1) or a day map (a sky of ~1 over a dark ground, a sun of 30 000)."""
    rng = np.random.default_rng(seed)
    sky, ground = (2e-4, 1e-5) if kind == "night" else (1.5, 0.02)
    rgb = np.where(np.arange(rows)[:, None, None] < rows // 2, sky, ground) * rng.random((rows, 2 * rows, 3))
    spots = [(11600.0, 2)] if kind == "night" else [(30000.0, 3)]  # the moon (the sun): a disc of a few pixels
    spots += [(float(rng.uniform(1, 50 if kind == "night" else 100)), 1) for _ in range(20)]  # lamps (or glints)
    for value, size in spots:
        r, c = int(rng.integers(4, rows - 4)), int(rng.integers(4, 2 * rows - 4))
        rgb[r : r + size, c : c + size] = value * np.array([1.0, 0.9, 0.7])
    return rgb.astype(np.float32)


def write_dwab(path: Path, rgb: np.ndarray) -> None:
    """As HDRI libraries compress their maps (the packaged ones: oiiotool's dwab:300): half floats, DWAB (lossy,
    8 x 8 DCT blocks in a perceptual encoding), which rings below zero next to the darkest pixels."""
    header = {"compression": OpenEXR.DWAB_COMPRESSION, "type": OpenEXR.scanlineimage, "dwaCompressionLevel": 300.0}
    channels = {name: rgb[..., i].astype(np.float16) for i, name in enumerate("RGB")}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def brute_force_share(rgb: np.ndarray) -> float:  # [H, W, 3] -> share of |L| dw held by the negative values
    rows, cols = rgb.shape[:2]
    total = negative = 0.0
    for i in range(rows):  # each row's solid angle per pixel: (cos of its top edge - cos of its bottom edge) dphi
        dw = (math.cos(i * math.pi / rows) - math.cos((i + 1) * math.pi / rows)) * 2 * math.pi / cols
        total += float(np.abs(rgb[i]).astype(np.float64).sum()) * dw
        negative += float(-rgb[i][rgb[i] < 0].astype(np.float64).sum()) * dw
    return negative / total


@pytest.mark.parametrize("kind", ["night", "day"])
def test_a_lossy_codecs_ringing_is_clamped_with_one_notice(tmp_path, capsys, kind):
    path = tmp_path / f"{kind} city.exr"
    write_dwab(path, panorama(512, kind))
    raw = read_raw(path)[..., :3]
    count = int((raw < 0).sum())
    assert count > 0, "the codec did not ring: the test would not test the clamp"
    share = brute_force_share(raw.numpy())
    assert 0 < share <= NEGATIVE_ENERGY_SHARE
    name, env = load_envmap(str(path), height=None)
    assert name == f"{kind}-city" and torch.equal(env, raw.clamp_min(0))
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"notice: {path}: {count} value{'s' * (count != 1)}, ") and "% of its energy" in lines[0]
    assert "clamped to 0" in lines[0]
    assert math.isclose(float(re.search(r"values?, ([\d.e+-]+) %", lines[0]).group(1)), 100 * share, rel_tol=0.05)
    # read again, and read as a light probe or an evaluation light: the same map, no second notice
    assert torch.equal(load_envmap(str(path), height=None)[1], env)
    torch.testing.assert_close(EnvironmentMap.from_file(path).map, env.clamp_min(1e-4), rtol=1e-5, atol=0)
    assert capsys.readouterr().err == ""


def test_a_night_map_would_have_been_refused_by_a_tolerance_of_the_mean(tmp_path):
    """Why the share of energy and not a tolerance in values: the night map's ringing lies deeper below zero than
    1 % of its mean, which the day map's does not."""
    for kind, deeper in (("night", True), ("day", False)):
        write_dwab(tmp_path / f"{kind}.exr", panorama(512, kind))
        raw = read_raw(tmp_path / f"{kind}.exr")[..., :3]
        assert (float(raw.min()) < -0.01 * float(raw.abs().mean())) == deeper, kind


@pytest.mark.parametrize("share", [0.01, 0.002])
def test_a_map_with_a_meaningful_share_of_negative_energy_is_refused_in_one_line(tmp_path, share):
    rgb = panorama(64, "day", seed=3)
    weights = np.array([math.cos(i * math.pi / 64) - math.cos((i + 1) * math.pi / 64) for i in range(64)])
    band = slice(40, 48)  # a band of the lower sky goes below zero, holding `share` of the energy
    positive = float((np.abs(rgb) * weights[:, None, None]).sum()) - float(
        (rgb[band] * weights[band, None, None]).sum()
    )
    rgb[band] = -share / (1 - share) * positive / float(weights[band].sum() * 128 * 3)
    assert math.isclose(brute_force_share(rgb), share, rel_tol=1e-3)
    path = tmp_path / "bad light.exr"
    write_raw(path, torch.from_numpy(rgb))
    for read in (lambda: load_envmap(str(path)), lambda: EnvironmentMap.from_file(path)):
        with pytest.raises(DataError) as caught:
            read()
        message = str(caught.value)
        assert "\n" not in message
        assert re.match(
            rf"^{re.escape(str(path))}: holds negative radiance \(\d+ values?, {100 * share:.3g} % ", message
        )


def test_the_share_is_weighed_by_solid_angle():
    rgb = torch.rand(16, 32, 3, generator=torch.Generator().manual_seed(4)) - 0.1
    count, share = negative_energy(rgb)
    assert count == int((rgb < 0).sum())
    assert math.isclose(share, brute_force_share(rgb.numpy()), rel_tol=1e-9)
    assert negative_energy(torch.zeros(4, 8, 3)) == (0, 0.0)


def hdri_paths() -> list[Path]:
    shared = sorted(SHARED_HDRI.glob("*.exr")) + sorted(SHARED_HDRI.glob("*.hdr")) if SHARED_HDRI.is_dir() else []
    return shared + list(lights.hdri_files().values())


@pytest.mark.parametrize("path", hdri_paths(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_shared_and_packaged_hdri_loads_with_at_most_one_notice(capsys, path):
    name, env = load_envmap(str(path), height=64)
    assert env.shape == (64, 128, 3) and env.min() >= 0 and torch.isfinite(env).all()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) <= 1, lines
    assert all(line.startswith(f"notice: {path}: ") for line in lines)


def test_the_shared_hdris_are_there_to_test():
    if not SHARED_HDRI.is_dir():
        pytest.skip(f"no shared test data at {SHARED_HDRI}")
    assert len(list(SHARED_HDRI.glob("*.exr"))) >= 6
