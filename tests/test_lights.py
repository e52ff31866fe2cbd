"""matspray.render.shade.lights: built-in environment maps, files, the packaged HDRI names, lookups and validation."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

import matspray
import matspray.render.shade.lights as lights
from matspray.data.images import read_raw, write_raw
from matspray.errors import ConfigError, DataError
from matspray.render.shade.latlong import direction_to_uv, pixel_directions, pixel_solid_angles
from matspray.render.shade.lights import (
    BUILTINS,
    builtin_envmap,
    check_envmap,
    default_relight_names,
    direction_from_angles,
    list_envmaps,
    load_envmap,
    lookup_envmap,
)


def irradiance(env: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:  # [H, 2H, 3], [3] -> [3]
    height = env.shape[0]
    d = pixel_directions(height, 2 * height, dtype=torch.float64)
    weight = pixel_solid_angles(height, 2 * height, dtype=torch.float64) * (d @ normal.double()).clamp_min(0.0)
    return (env.double() * weight[..., None]).sum((0, 1))


@pytest.mark.parametrize("name", list(BUILTINS))
def test_builtins_are_finite_positive_latlong_maps(name):
    env = builtin_envmap(name, 16)
    assert env.shape == (16, 32, 3) and env.dtype == torch.float32
    check_envmap(env)
    assert env.min() > 0.0
    assert irradiance(env, torch.tensor([0.0, 0.0, 1.0])).min() > 0.5  # every built-in lights the scene


@pytest.mark.parametrize("name", list(BUILTINS))
def test_builtin_irradiance_does_not_depend_on_map_size(name):
    """4 x 4 supersampling per pixel keeps small suns' energy at coarse sizes."""
    for normal in (torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.6, -0.8, 0.0])):
        coarse, fine = irradiance(builtin_envmap(name, 64), normal), irradiance(builtin_envmap(name, 256), normal)
        torch.testing.assert_close(coarse, fine, rtol=0.02, atol=1e-3)


def test_sky_sun_sits_where_the_convention_says():
    env = builtin_envmap("sky", 64)
    row, col = divmod(int(env.sum(-1).argmax()), env.shape[1])
    u, v = direction_to_uv(direction_from_angles(35.0, 40.0).float()).tolist()
    assert abs((col + 0.5) / 128 - u) < 2 / 128 and abs((row + 0.5) / 64 - v) < 2 / 64
    # up is +z: the sky above the horizon is brighter than the ground below it
    assert env[:16].mean() > 1.5 * env[-16:].mean()


def test_default_relight_lights_differ_from_the_training_light():
    assert default_relight_names("sky") == ["studio", "sunset"]
    assert default_relight_names("studio") == ["sunset", "sky"]
    assert default_relight_names("forest") == ["studio", "sunset"]
    assert list_envmaps()[: len(BUILTINS)] == list(BUILTINS)


def test_load_exr_and_hdr_files_by_path(tmp_path):
    values = torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(1)) * 5 + 0.1
    write_raw(tmp_path / "My Light.exr", values)
    name, env = load_envmap(tmp_path / "My Light.exr", height=None)
    assert name == "my-light" and torch.equal(env, values)
    write_raw(tmp_path / "room.hdr", values)
    name, env = load_envmap(str(tmp_path / "room.hdr"), height=None)
    assert name == "room"
    # RGBE: three 8-bit mantissas share one exponent, so the error is relative to a pixel's largest channel
    assert ((env - values).abs() <= values.amax(-1, keepdim=True) / 128).all()
    d = pixel_directions(32, 64)
    smooth = torch.stack([2 + d[..., 2], 2 + d[..., 0], 2 - d[..., 1]], -1)
    write_raw(tmp_path / "smooth.exr", smooth)
    _, small = load_envmap(tmp_path / "smooth.exr", height=8)  # resampled to the working size
    assert small.shape == (8, 16, 3)
    for normal in (torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0])):
        torch.testing.assert_close(irradiance(small, normal), irradiance(smooth, normal), rtol=0.02, atol=0.0)


def test_bad_files_and_names_are_clear_errors(tmp_path):
    write_raw(tmp_path / "square.exr", torch.ones(8, 8, 3))
    with pytest.raises(DataError, match="square.exr: is 8x8 pixels but a lat-long environment map is twice as wide"):
        load_envmap(tmp_path / "square.exr")
    (tmp_path / "broken.exr").write_bytes(b"garbage")
    with pytest.raises(DataError, match="broken.exr: cannot read image"):
        load_envmap(tmp_path / "broken.exr")
    (tmp_path / "light.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match="must be .exr or .hdr"):
        load_envmap(tmp_path / "light.png")
    with pytest.raises(DataError, match="missing.hdr: file does not exist"):
        load_envmap(tmp_path / "missing.hdr")
    with pytest.raises(ConfigError, match="unknown environment map 'moon'.*built-ins: sky, studio, sunset, overcast;"):
        load_envmap("moon")
    with pytest.raises(ConfigError, match="height must be an integer"):
        load_envmap("sky", height=2)


PACKAGED = ("city", "forest", "interior", "studio-small", "sunrise", "venice-sunset")
SHARED_NAME = {"studio-small": "studio", "venice-sunset": "sunset"}  # the shared test data keeps Poly Haven's old names


def test_packaged_hdri_names_resolve_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing beside the working directory: the lights come from the package
    assert lights.HDRI_FOLDER == Path(matspray.__file__).resolve().parent / "hdri"  # the package's own data
    assert sorted(lights.hdri_files()) == list(PACKAGED)
    assert list_envmaps() == list(BUILTINS) + [name for name in PACKAGED if name not in BUILTINS]
    name, env = load_envmap("forest", height=16)
    assert name == "forest" and env.shape == (16, 32, 3) and torch.isfinite(env).all() and env.min() >= 0
    assert not set(BUILTINS) & set(lights.hdri_files())  # no name means two lights
    assert torch.equal(load_envmap("sky", height=8)[1], builtin_envmap("sky", 8))  # built-ins win over files


def test_packaged_hdris_are_the_shared_test_data(monkeypatch):
    shared = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "hdri"
    if not shared.is_dir():
        pytest.skip(f"no shared test data at {shared}")
    for name in PACKAGED:
        assert (lights.HDRI_FOLDER / f"{name}.exr").read_bytes() == (
            shared / f"{SHARED_NAME.get(name, name)}.exr"
        ).read_bytes()


def test_without_packaged_files_names_give_a_clear_error(monkeypatch):
    monkeypatch.setattr(lights, "hdri_folders", lambda: [])
    assert list_envmaps() == list(BUILTINS)
    with pytest.raises(
        ConfigError, match=r"^unknown environment map 'forest': .*\(built-ins: sky, studio, sunset, overcast\)$"
    ):
        load_envmap("forest")
    with pytest.raises(ConfigError, match=r"HDRIs: city, forest, interior, studio-small, sunrise, venice-sunset\)$"):
        monkeypatch.undo()
        load_envmap("moon")


def test_codec_ringing_below_zero_is_clamped():
    # the packaged forest.exr holds a few values a little below 0 (its lossy codec's ringing)
    raw = read_raw(lights.HDRI_FOLDER / "forest.exr")[..., :3]
    assert -0.01 < float(raw.min()) < 0
    env = lights.read_envmap_file(lights.HDRI_FOLDER / "forest.exr", height=None)
    assert float(env.min()) >= 0 and torch.equal(env, raw.clamp_min(0))


@pytest.mark.parametrize(
    "value, message",
    [
        (
            -1.0,
            r"holds negative radiance \(1 value, [\d.]+ % of its energy, down to -1\) \(a light is >= 0 everywhere",
        ),
        (-0.5, r"holds negative radiance \(1 value, [\d.]+ % of its energy, down to -0.5\)"),
        (float("nan"), r"holds 1 NaN or Inf values"),
        (float("inf"), r"holds 1 NaN or Inf values"),
    ],
)
def test_non_physical_light_files_are_refused_in_one_line(tmp_path, value, message):
    values = torch.full((4, 8, 3), 2.0)
    values[1, 2, 0] = value
    path = tmp_path / "bad light.exr"
    write_raw(path, values)
    with pytest.raises(DataError, match=f"^{re.escape(str(path))}: {message}") as caught:
        load_envmap(str(path))
    assert "\n" not in str(caught.value)
    values[1, 2, 0] = -0.001  # a codec's ringing (a millionth of the energy): clamped
    write_raw(path, values)
    assert float(load_envmap(str(path), height=None)[1][1, 2, 0]) == 0.0


def test_lookup_returns_pixel_values_at_centres_and_wraps_in_longitude():
    env = torch.rand(6, 12, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    centres = pixel_directions(6, 12, dtype=torch.float64)
    torch.testing.assert_close(lookup_envmap(env, centres), env)
    # half way between the last and the first column, on a row centre: the mean of the two
    row = 2
    theta = (row + 0.5) / 6 * math.pi
    seam = torch.tensor([-math.sin(theta) * math.cos(math.pi), 0.0, math.cos(theta)], dtype=torch.float64)  # u = 0
    torch.testing.assert_close(lookup_envmap(env, seam), 0.5 * (env[row, 0] + env[row, -1]))


def test_check_envmap_rejects_bad_maps():
    with pytest.raises(DataError, match="expected a lat-long map \\[H, 2H, 3\\]"):
        check_envmap(torch.ones(4, 4, 3))
    with pytest.raises(DataError, match="negative, NaN or Inf"):
        check_envmap(torch.full((4, 8, 3), -1.0))
