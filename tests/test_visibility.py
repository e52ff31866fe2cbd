import math

import pytest
import torch

from matspray.gaussians import Gaussians
from matspray.method.asset import Asset, read_asset, write_asset
from matspray.method.relight import render_gbuffer
from matspray.render.raster.gbuffer import orient_normals
from matspray.render.raster.rasterize import rasterize
from matspray.render.shade.deferred import shade
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.visibility import (
    VisibilityConfig,
    bake_visibility,
    gaussian_shadows,
    light_cells,
    open_side,
    shadow_factors,
    transmittance_at,
    visibility_directions,
)
from tests.scenes import ring_cameras, sky_map, sphere_of_disks

SMALL = VisibilityConfig(rows=4, resolution=64)


def test_transmittance_is_one_minus_the_weights_in_front_on_the_queried_pixel():
    # pixel 0: hits at depths 0.2 (w 0.5) and 0.6 (w 0.3); pixel 2: one hit at 0.4 (w 0.9)
    keys = torch.tensor([0 + 0.2 / 2, 0 + 0.6 / 2, 2 + 0.4 / 2], dtype=torch.float64)
    cumulative = torch.tensor([0.0, 0.5, 0.8, 1.7], dtype=torch.float64)
    pixel = torch.tensor([0, 0, 0, 1, 2, 2])
    depth = torch.tensor([0.1, 0.5, 0.9, 0.9, 0.3, 0.5])
    expected = torch.tensor([1.0, 0.5, 0.2, 1.0, 1.0, 0.1], dtype=torch.float64)
    torch.testing.assert_close(transmittance_at(keys, cumulative, pixel, depth), expected)


def with_centre_disk(gaussians: Gaussians) -> Gaussians:
    """The disk sphere plus one small Gaussian at its centre, which no direction can see."""
    centre = Gaussians(
        torch.zeros(1, 3),
        torch.full((1, 3), math.log(0.05)),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        torch.full((1,), 4.0),
        torch.zeros(1, 1, 3),
    )
    return Gaussians(
        *(
            torch.cat([getattr(gaussians, f), getattr(centre, f)])
            for f in ("means", "log_scales", "quats", "opacity_logits", "sh")
        )
    )


def test_closed_sphere_sees_out_only_through_its_own_side():
    gaussians, normals, _ = sphere_of_disks()
    visibility = bake_visibility(with_centre_disk(gaussians), SMALL)  # [N + 1, D]
    directions, _ = visibility_directions(SMALL.rows)
    assert visibility.shape == (len(gaussians) + 1, len(directions))
    assert visibility[-1].max() < 0.05  # the centre is enclosed
    facing = normals @ directions.t()  # [N, D]
    outward = visibility[:-1][facing > 0.5]
    inward = visibility[:-1][facing < -0.5]
    assert outward.mean() > 0.9 and (outward > 0.5).float().mean() > 0.95
    assert inward.mean() < 0.05


def test_a_disk_above_shadows_the_point_below_only_from_above():
    # a wide opaque disk at z = 1 over a small one at z = 0
    means = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    scales = torch.tensor([[3.0, 3.0, 0.01], [0.05, 0.05, 0.01]])
    gaussians = Gaussians(
        means, scales.log(), torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2), torch.full((2,), 6.0), torch.zeros(2, 1, 3)
    )
    visibility = bake_visibility(gaussians, VisibilityConfig(rows=4, resolution=96))
    directions, _ = visibility_directions(4)
    up, down = directions[:, 2].argmax(), directions[:, 2].argmin()
    assert visibility[1, up] < 0.05 and visibility[1, down] > 0.95
    assert visibility[0, up] > 0.95  # nothing above the big disk


def test_shadow_factors_are_one_when_everything_is_visible_and_zero_when_nothing_is():
    light = sky_map(8)
    n = 50
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    view_dirs = torch.nn.functional.normalize(
        normals + 0.3 * torch.randn(n, 3, generator=torch.Generator().manual_seed(1)), dim=-1
    )
    roughness = torch.rand(n, generator=torch.Generator().manual_seed(2))
    d = 2 * 8 * 8
    torch.testing.assert_close(shadow_factors(torch.ones(n, d), normals, view_dirs, roughness, light), torch.ones(n, 6))
    torch.testing.assert_close(
        shadow_factors(torch.zeros(n, d), normals, view_dirs, roughness, light), torch.zeros(n, 6)
    )


def test_diffuse_shadow_factor_is_the_cosine_weighted_visible_share_of_a_uniform_light():
    rows = 6
    directions, solid_angles = visibility_directions(rows)
    normal = torch.tensor([[0.0, 0.0, 1.0]])
    visibility = (directions[:, 0] > 0).float()[None]  # only the half-space x > 0 is visible
    factors = shadow_factors(visibility, normal, normal, torch.tensor([0.5]), torch.ones(rows, 2 * rows, 3))
    cosine = directions[:, 2].clamp_min(0) * solid_angles
    expected = float((cosine * visibility[0]).sum() / cosine.sum())
    torch.testing.assert_close(factors[0, :3], torch.full((3,), expected))
    assert abs(expected - 0.5) < 0.02  # half the hemisphere, by symmetry


def test_a_normal_turned_into_the_object_is_turned_back_to_its_open_side():
    rows = 6
    directions, solid_angles = visibility_directions(rows)
    outward = torch.nn.functional.normalize(torch.tensor([[1.0, 0.2, 0.3], [-0.4, 0.9, -0.1]]), dim=-1)
    visibility = (outward @ directions.t() > 0).float()  # [2, D] the inside of each plane is hidden
    for sign in (1.0, -1.0):
        turned = open_side(visibility, sign * outward @ directions.t(), solid_angles) * sign * outward
        torch.testing.assert_close(turned, outward)
    # unshadowed whichever way the viewer turned the normal; before, the inward turn read 0 (all hidden)
    light = sky_map(rows)
    for sign in (1.0, -1.0):
        factors = shadow_factors(visibility, sign * outward, outward, torch.tensor([0.5, 0.8]), light)
        torch.testing.assert_close(factors, torch.ones(2, 6))


def test_the_sphere_is_shadowed_alike_whichever_way_its_normals_are_turned():
    gaussians, normals, materials = sphere_of_disks()
    outward = torch.where(((normals * gaussians.means).sum(-1, keepdim=True) < 0), -normals, normals)
    visibility = bake_visibility(gaussians, SMALL)
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    camera = ring_cameras(1, 32)[0]
    turned = orient_normals(outward, gaussians.means, camera)  # towards the camera: inward on the far side
    assert bool((turned != outward).any())
    torch.testing.assert_close(
        gaussian_shadows(visibility, turned, gaussians.means, materials, camera, light),
        gaussian_shadows(visibility, outward, gaussians.means, materials, camera, light),
    )


def test_shading_with_unit_shadow_equals_unshadowed_shading():
    env = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    base = torch.rand(10, 3)
    rough, metal = torch.rand(10), torch.rand(10)
    normals = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    view_dirs = torch.nn.functional.normalize(normals + 0.2 * torch.randn(10, 3), dim=-1)
    plain = shade(base, rough, metal, normals, view_dirs, env)
    torch.testing.assert_close(shade(base, rough, metal, normals, view_dirs, env, torch.ones(10, 6)), plain)
    assert torch.all(shade(base, rough, metal, normals, view_dirs, env, torch.full((10, 6), 0.5)) <= plain + 1e-6)


def test_shadowed_g_buffer_of_a_sphere_is_close_to_unshadowed_where_it_faces_the_camera():
    gaussians, normals, materials = sphere_of_disks()
    asset = Asset(gaussians, materials, normals, bake_visibility(gaussians, SMALL))
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    camera = ring_cameras(1, 32)[0]
    gbuffer = render_gbuffer(asset, camera, light)
    assert gbuffer.shadow is not None and gbuffer.shadow.shape == (32, 32, 6)
    covered = gbuffer.alpha > 0.9
    # a convex object barely shadows itself: the diffuse factor is high where it is seen head on
    assert gbuffer.shadow[covered][:, :3].median() > 0.85
    shadows = gaussian_shadows(asset.visibility, normals, gaussians.means, materials, camera, light)
    assert shadows.shape == (len(gaussians), 6) and shadows.min() >= 0 and shadows.max() <= 1


def test_the_specular_shadow_kernel_reads_the_roughness_channel_not_the_metallic():
    # rough dielectric: roughness 0.95 gives a broad specular kernel (kappa ~ 0.6), metallic 0 would give
    # the sharpest one allowed (kappa 1.5); with half the directions blocked the two factors differ
    gaussians, normals, materials = sphere_of_disks(n=60)
    materials = materials.clone()
    materials[:, 3], materials[:, 4] = 0.95, 0.0
    rows = 4
    visibility = (torch.arange(2 * rows * rows) % 2).float().expand(len(gaussians), -1).contiguous()
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    camera = ring_cameras(1, 32)[0]
    oriented = orient_normals(normals, gaussians.means, camera)
    view_dirs = torch.nn.functional.normalize(camera.center.to(gaussians.means) - gaussians.means, dim=-1)
    cells = light_cells(light, rows)
    expected = shadow_factors(visibility, oriented, view_dirs, materials[:, 3], cells)
    with_metallic = shadow_factors(visibility, oriented, view_dirs, materials[:, 4], cells)
    assert (expected[:, 3:] - with_metallic[:, 3:]).abs().max() > 1e-3  # the test can tell the two apart
    torch.testing.assert_close(
        gaussian_shadows(visibility, oriented, gaussians.means, materials, camera, light), expected
    )
    # the relit G-buffer blends exactly those factors
    gbuffer = render_gbuffer(Asset(gaussians, materials, normals, visibility), camera, light)
    blended = rasterize(gaussians, camera, expected)
    covered = blended.alpha > 0.5
    torch.testing.assert_close(
        gbuffer.shadow[covered],
        (blended.features / blended.alpha[..., None].clamp_min(1e-8))[covered],
        atol=1e-4,
        rtol=1e-4,
    )


def test_visibility_round_trips_with_the_asset_and_a_wrong_count_is_refused(tmp_path):
    from types import SimpleNamespace

    from matspray.errors import DataError

    gaussians, normals, materials = sphere_of_disks(n=40)
    visibility = torch.rand(40, 32)
    result = SimpleNamespace(
        materials=materials, normals=normals, envmap=None, source=None, history=[], visibility=visibility
    )
    write_asset(tmp_path, gaussians, result)
    asset = read_asset(tmp_path)
    torch.testing.assert_close(asset.visibility, visibility, atol=1 / 510 + 1e-6, rtol=0)
    torch.save(
        {"format": "matspray-visibility-1", "values": torch.zeros(7, 32, dtype=torch.uint8)}, tmp_path / "visibility.pt"
    )
    with pytest.raises(DataError, match="visibility.pt.*7, 32.*40 Gaussians"):
        read_asset(tmp_path)
    write_asset(tmp_path, gaussians, SimpleNamespace(**{**result.__dict__, "visibility": None}))
    assert read_asset(tmp_path).visibility is None  # the stale file is gone with the asset that used it


def test_shadow_factor_gradients_are_finite_for_fully_rough_gaussians():
    light = EnvironmentMap.from_tensor(sky_map(8).float())
    rows = 4
    rough = torch.tensor([1.0, 1.0, 0.5], requires_grad=True)
    normals = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 0.8], [0.0, 0.3, 0.9]]), dim=-1)
    view_dirs = torch.nn.functional.normalize(torch.tensor([[0.3, 0.0, 0.9], [0.0, 0.4, 0.9], [0.2, 0.2, 0.9]]), dim=-1)
    visibility = torch.rand(3, 2 * rows * rows, generator=torch.Generator().manual_seed(0))
    from matspray.render.shade.visibility import light_cells

    shadow_factors(visibility, normals, view_dirs, rough, light_cells(light, rows)).sum().backward()
    assert torch.isfinite(rough.grad).all()
