"""The learnable environment map: validation, lookups, prefiltering against brute-force sums, gradients."""

import math

import pytest
import torch

from matspray.errors import ConfigError, DataError
from matspray.render.shade.brdf import ggx_ndf, roughness_to_alpha, smith_visibility
from matspray.render.shade.envmap import (
    DEFAULT_LEVELS,
    EnvironmentMap,
    downsample_latlong,
    irradiance_map,
    level_height,
    prefilter_latlong,
    prefilter_specular,
    sample_latlong,
)
from matspray.render.shade.latlong import direction_to_uv, pixel_directions, pixel_solid_angles, uv_to_direction

f64 = torch.float64


def smooth_map(height: int, dtype=f64):
    """A sky-like map: a vertical gradient, a soft horizon and one broad bright blob."""
    d = pixel_directions(height, 2 * height, dtype=dtype)
    z = d[..., 2:]
    sky = torch.tensor([0.3, 0.5, 0.9], dtype=dtype) * (0.6 + 0.4 * z)
    ground = torch.tensor([0.2, 0.15, 0.1], dtype=dtype) * torch.sigmoid(-z / 0.15)
    blob_dir = torch.tensor([0.5, 0.3, 0.6], dtype=dtype)
    blob = torch.exp(((d * blob_dir / blob_dir.norm()).sum(-1, keepdim=True) - 1) / 0.08)
    return sky + ground + 4.0 * blob * torch.tensor([1.0, 0.9, 0.7], dtype=dtype)


def random_map(height: int, seed: int = 0):
    return torch.rand(height, 2 * height, 3, generator=torch.Generator().manual_seed(seed), dtype=f64) + 0.1


# ------------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize("shape", [(16, 16, 3), (16, 32), (16, 32, 4), (8, 17, 3)])
def test_non_latlong_shapes_are_rejected(shape):
    with pytest.raises(DataError, match=r"lat-long with width = 2 x height.*got shape"):
        EnvironmentMap.from_tensor(torch.ones(shape))


def test_bad_values_are_rejected():
    bad = torch.ones(4, 8, 3)
    bad[1, 2, 0] = float("nan")
    with pytest.raises(DataError, match="NaN or Inf"):
        EnvironmentMap.from_tensor(bad)
    with pytest.raises(DataError, match="negative radiance"):
        EnvironmentMap.from_tensor(-torch.ones(4, 8, 3))
    with pytest.raises(ConfigError, match="strictly increasing"):
        EnvironmentMap.constant(1.0, 4).prefilter(levels=(0.5, 0.2))


def test_file_with_wrong_aspect_is_rejected_naming_the_file(tmp_path):
    from matspray.data.images import write_image

    path = tmp_path / "square.exr"
    write_image(path, torch.ones(8, 8, 3))
    with pytest.raises(DataError, match=r"square\.exr: environment map must be lat-long"):
        EnvironmentMap.from_file(path)


def test_save_and_load_round_trip(tmp_path):
    env = EnvironmentMap.from_tensor(smooth_map(8).float() * 10)
    env.save(tmp_path / "env.exr")
    back = EnvironmentMap.from_file(tmp_path / "env.exr")
    torch.testing.assert_close(back.map, env.map.detach(), rtol=1e-5, atol=1e-6)
    assert not back.log_map.requires_grad  # maps loaded for relighting are fixed by default


# ------------------------------------------------------------------------------------------ the module
def test_map_is_positive_and_learnable():
    target = smooth_map(8).float()
    env = EnvironmentMap.from_tensor(target)
    torch.testing.assert_close(env.map, target, rtol=1e-5, atol=1e-6)
    assert env.height == 8 and env.log_map.requires_grad
    env.log_map.data -= 50.0  # any parameter value is a valid, positive map
    assert torch.all(env.map > 0)
    constant = EnvironmentMap.constant([1.0, 2.0, 3.0], height=4)
    assert constant.map.shape == (4, 8, 3) and torch.allclose(constant.map[2, 5], torch.tensor([1.0, 2.0, 3.0]))


def test_downsample_keeps_total_power_and_height_option():
    source = random_map(16)
    small = downsample_latlong(source, 4)
    power = lambda m: (m * pixel_solid_angles(m.shape[0], m.shape[1], dtype=f64)[..., None]).sum((0, 1))  # noqa: E731
    torch.testing.assert_close(power(small), power(source))
    assert EnvironmentMap.from_tensor(source, height=8).height == 8
    assert EnvironmentMap.from_tensor(source, height=64).height == 16  # never upsampled


# ------------------------------------------------------------------------------------------ lookups
def test_sample_latlong_hits_pixel_centres_and_wraps():
    source = random_map(8)
    torch.testing.assert_close(sample_latlong(source, pixel_directions(8, 16, dtype=f64)), source)
    # u = 0 lies half way between the last and the first column
    d = uv_to_direction(torch.tensor([[0.0, 4.5 / 8]], dtype=f64))
    torch.testing.assert_close(sample_latlong(source, d)[0], (source[4, 0] + source[4, -1]) / 2)
    # straight up: the mean of the top row, from any side
    up = torch.tensor([[0.0, 0.0, 1.0], [1e-5, 0.0, 1.0]], dtype=f64)
    torch.testing.assert_close(sample_latlong(source, up)[0], source[0].mean(0))
    torch.testing.assert_close(sample_latlong(source, up)[1], source[0].mean(0), atol=1e-4, rtol=0)


def test_sample_latlong_matches_bilinear_by_hand():
    source = random_map(8)
    uv = torch.tensor([[0.3, 0.4], [0.81, 0.22]], dtype=f64)
    got = sample_latlong(source, uv_to_direction(uv))
    for (u, v), value in zip(uv.tolist(), got):
        x, y = u * 16 - 0.5, v * 8 - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        expected = (
            source[y0, x0] * (1 - fx) * (1 - fy)
            + source[y0, x0 + 1] * fx * (1 - fy)
            + source[y0 + 1, x0] * (1 - fx) * fy
            + source[y0 + 1, x0 + 1] * fx * fy
        )
        torch.testing.assert_close(value, expected)


# ------------------------------------------------------------------------------------------ prefiltering
def brute_force(source, out_dirs, weight):
    """Sums over every pixel of `source` [H, W, 3] with weights weight(cos angle) times solid angle, for
    each direction of out_dirs [O, 3]: the weighted totals [O, 3] and the weight sums [O]."""
    dirs = pixel_directions(source.shape[0], source.shape[1], dtype=f64).reshape(-1, 3)
    dw = pixel_solid_angles(source.shape[0], source.shape[1], dtype=f64).reshape(-1)
    cos = out_dirs @ dirs.T  # [O, P]
    w = weight(cos) * dw
    return w @ source.reshape(-1, 3), w.sum(-1)


def test_irradiance_equals_the_cosine_sum_at_every_output_pixel():
    source = random_map(16)
    got = irradiance_map(source, height=4)  # stride 4: output pixels span 4 x 4 input pixels
    assert got.shape == (4, 8, 3)
    total, norm = brute_force(source, pixel_directions(4, 8, dtype=f64).reshape(-1, 3), lambda c: c.clamp_min(0))
    assert torch.allclose(norm, torch.full_like(norm, math.pi), rtol=5e-3)  # the plain sum is within 0.5 % of pi ...
    torch.testing.assert_close(got.reshape(-1, 3), total / norm[:, None] * math.pi)  # ... and is rescaled to it


@pytest.mark.parametrize("roughness", [0.3, 0.9])
def test_specular_level_equals_the_normalised_lobe_sum(roughness):
    source = random_map(32)
    got = prefilter_specular(source, roughness)
    assert got.shape[0] == level_height(roughness, 32) == (32 if roughness < 0.5 else 16)
    alpha = roughness_to_alpha(torch.tensor(roughness, dtype=f64))

    def lobe(c):
        return (
            ggx_ndf(torch.sqrt(((1 + c) / 2).clamp_min(0)), alpha)
            * smith_visibility(c, torch.ones_like(c), alpha)
            * c.clamp_min(0)
        )

    out_dirs = pixel_directions(got.shape[0], got.shape[1], dtype=f64).reshape(-1, 3)
    total, norm = brute_force(source, out_dirs, lobe)
    torch.testing.assert_close(got.reshape(-1, 3), total / norm[:, None])


def test_constant_environment_prefilters_to_itself():
    pre = EnvironmentMap.constant(2.5, height=16, dtype=f64).prefilter()
    for level in pre.specular:
        torch.testing.assert_close(level, torch.full_like(level, 2.5))
    torch.testing.assert_close(pre.irradiance, torch.full_like(pre.irradiance, 2.5 * math.pi))


def test_lookup_specular_interpolates_between_levels():
    pre = prefilter_latlong(smooth_map(16), levels=(0.2, 0.6, 1.0))
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -0.2, 0.8], [-0.6, 0.1, -0.2]], dtype=f64), dim=-1)
    at = lambda r: pre.lookup_specular(d, torch.full((2,), r, dtype=f64))  # noqa: E731
    level = lambda i: sample_latlong(pre.specular[i], d)  # noqa: E731
    torch.testing.assert_close(at(0.6), level(1))
    torch.testing.assert_close(at(0.7), 0.75 * level(1) + 0.25 * level(2))
    torch.testing.assert_close(at(0.05), level(0))  # clamped to the range of levels


def test_prefiltering_all_levels_at_once_equals_each_level_alone():
    source = random_map(32)
    pre = prefilter_latlong(source)
    assert len(pre.specular) == len(DEFAULT_LEVELS)
    for level, roughness in zip(pre.specular, DEFAULT_LEVELS):
        torch.testing.assert_close(level, prefilter_specular(source, roughness))
    torch.testing.assert_close(pre.irradiance, irradiance_map(source))


def test_lookups_in_the_prefiltered_maps_sample_each_map_bilinearly_across_the_poles():
    pre = prefilter_latlong(random_map(16), levels=(0.2, 0.6, 1.0))
    g = torch.Generator().manual_seed(2)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=f64), dim=-1)
    d[:4] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-5, 0.0, 1.0], [0.3, 0.0, -1.0]], dtype=f64)
    n = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=f64), dim=-1)
    for i, roughness in enumerate(pre.levels):
        r = torch.full((200,), roughness, dtype=f64)
        torch.testing.assert_close(pre.lookup_specular(d, r), sample_latlong(pre.specular[i], d))
        torch.testing.assert_close(pre.lookup_specular(3.0 * d, r), pre.lookup_specular(d, r))  # any length
    torch.testing.assert_close(pre.lookup_diffuse(n), sample_latlong(pre.irradiance, n))
    r = torch.rand(200, generator=g, dtype=f64)
    specular, diffuse = pre.lookup(d, r, n)
    torch.testing.assert_close(specular, pre.lookup_specular(d, r))
    torch.testing.assert_close(diffuse, pre.lookup_diffuse(n))


def test_prefilter_and_lookup_gradcheck():
    log_map = (random_map(2) * 0.5).log().requires_grad_(True)  # a 2 x 4 map keeps the numerical Jacobian cheap
    d = torch.nn.functional.normalize(
        torch.tensor([[0.3, -0.2, 0.8], [-0.6, 0.1, -0.2], [0.1, 0.9, 0.2]], dtype=f64), dim=-1
    )
    d.requires_grad_(True)
    r = torch.tensor([0.35, 0.8, 0.55], dtype=f64, requires_grad=True)

    def chain(log_map, d, r):
        pre = prefilter_latlong(log_map.exp(), levels=(0.3, 0.6, 1.0))
        return pre.lookup_specular(d, r), pre.lookup_diffuse(d), *pre.lookup(d, r, d.flip(-1))

    assert torch.autograd.gradcheck(chain, (log_map, d, r), fast_mode=True)


def test_gradients_reach_the_module_parameter():
    env = EnvironmentMap.from_tensor(smooth_map(8).float())
    d = torch.nn.functional.normalize(torch.randn(20, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    loss = env.lookup_specular(d, torch.full((20,), 0.5)).sum() + env.lookup_diffuse(d).sum() + env.radiance(d).sum()
    loss.backward()
    assert torch.isfinite(env.log_map.grad).all() and (env.log_map.grad.abs() > 0).float().mean() > 0.5


def test_lookup_gradients_are_finite_at_the_poles():
    source = random_map(4).requires_grad_(True)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=f64, requires_grad=True)
    sample_latlong(source, d).sum().backward()
    assert torch.isfinite(d.grad).all() and torch.isfinite(source.grad).all()
    assert torch.allclose(direction_to_uv(d.detach())[:, 1], torch.tensor([0.0, 1.0], dtype=f64))
