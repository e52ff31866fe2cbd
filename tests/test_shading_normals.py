"""Shading normals refined by the rendering loss (matspray.method.refine.normals, used by
matspray.method.refine.loop)."""

import pytest
import torch
import torch.nn.functional as F

from matspray.errors import SettingError
from matspray.geometry.losses import normal_map_loss
from matspray.geometry.normals import angular_error_degrees
from matspray.method.asset import Asset
from matspray.method.refine.loop import RefineConfig, RefineInputs, refine
from matspray.method.refine.normals import (
    ShadingNormals,
    angle_change_degrees,
    nearest_neighbours,
    normal_prior,
    smoothed_normals,
)
from matspray.method.relight import render_gbuffer
from matspray.render.shade.envmap import EnvironmentMap
from tests.scenes import lift_material_scene, material_scene, sky_map

BOUNDS = torch.tensor([[-1.2] * 3, [1.2] * 3])


@pytest.fixture(scope="module")
def scene_with_tilted_normals():
    """The disk sphere's views (rendered with its true normals, materials and light), lifted, and the same normals
    each tilted by ~25 degrees in a random direction: the geometry's normals a refinement starts from."""
    gaussians, normals, materials, views, maps = material_scene(n_views=8)
    lifted = lift_material_scene(gaussians, views, maps)
    kept, true_normals = gaussians.subset(lifted.kept), normals[lifted.kept]
    generator = torch.Generator().manual_seed(3)
    side = F.normalize(torch.linalg.cross(true_normals, torch.randn(true_normals.shape, generator=generator)), dim=-1)
    tilted = F.normalize(true_normals + 0.47 * side, dim=-1)  # tan(25 deg) = 0.47
    return kept, true_normals, tilted, views, maps, lifted, materials[lifted.kept]


def known_light() -> EnvironmentMap:  # the light the views were rendered under, at the same size
    return EnvironmentMap.from_tensor(sky_map(), learnable=False)


def refine_tilted(scene, start=None, normal_maps=None, true_materials=False, **settings):
    """Refine `full` from the tilted normals (or `start`) under the true light; with `true_materials` every view's
    lifted value is the Gaussian's true material and the merger is frozen, so only the normals can explain the
    photos."""
    gaussians, _, tilted, views, maps, lifted, materials = scene
    values = materials[:, None].expand(-1, len(views), -1).contiguous() if true_materials else lifted.values
    start = tilted if start is None else start
    inputs = RefineInputs(gaussians, start, values, lifted.seen, views, maps, BOUNDS, normal_maps=normal_maps)
    frozen_materials = {"merger_lr": 0.0, "material_weight": 0.0} if true_materials else {}
    config = RefineConfig(
        **{
            "iterations": 150,
            "envmap_height": 8,
            "light_warmup": 0,
            "seed": 0,
            "normal_neighbours": 0,  # the tests of refinement's own normals start from the tilted ones as they are
            **frozen_materials,
            **settings,
        }
    )
    return refine(inputs, config, progress=False, light=known_light())


def mean_error(normals, truth) -> float:
    return float(angle_change_degrees(normals, truth).mean())


def rendered_error(scene, normals) -> float:
    """Mean angle (degrees) between the blended normals of `normals` and of the true ones, over the views' object
    pixels: what shading sees (one pixel blends several Gaussians, so single normals are not all determined)."""
    gaussians, truth, _, views, *_ = scene
    errors = []
    for view in views:
        zeros = torch.zeros(len(gaussians), 5)
        got, want = (render_gbuffer(Asset(gaussians, zeros, n), view.camera) for n in (normals, truth))
        errors.append(angular_error_degrees(got.normals, want.normals)[want.alpha > 0.5])
    return float(torch.cat(errors).mean())


def test_normal_prior_is_zero_when_aligned_either_way_and_one_at_right_angles():
    n = F.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    assert float(normal_prior(n, n)) == pytest.approx(0.0, abs=1e-12)
    assert float(normal_prior(n, -n)) == pytest.approx(0.0, abs=1e-12)
    perpendicular = F.normalize(torch.linalg.cross(n, torch.randn(50, 3, dtype=torch.float64)), dim=-1)
    assert float(normal_prior(n, perpendicular)) == pytest.approx(1.0, abs=1e-12)
    empty = torch.zeros(0, 3, requires_grad=True)
    assert normal_prior(empty, empty).item() == 0.0 and normal_prior(empty, empty).requires_grad


def test_the_shading_normals_gradient_matches_finite_differences():
    initial = F.normalize(torch.randn(6, 3, dtype=torch.float64), dim=-1)
    targets = F.normalize(torch.randn(6, 3, dtype=torch.float64), dim=-1)
    shading = ShadingNormals(initial).double()
    weights = torch.randn(6, 3, dtype=torch.float64)

    def loss(direction):
        normals = F.normalize(direction, dim=-1, eps=1e-12)
        return normal_prior(normals, targets) + (normals * weights).sum()

    assert torch.allclose(shading(), initial)
    assert torch.autograd.gradcheck(loss, (shading.direction.detach().clone().requires_grad_(),))


def test_the_photo_loss_turns_tilted_normals_towards_the_true_ones_and_leaves_true_ones(scene_with_tilted_normals):
    """With the true materials and light nothing but the normals is wrong: refinement halves their rendered error,
    and started at the truth it stays there. (With the merger's imperfect materials the normals also absorb
    material errors: hence the prior.)"""
    truth, tilted = scene_with_tilted_normals[1:3]
    before = rendered_error(scene_with_tilted_normals, tilted)
    turned = refine_tilted(scene_with_tilted_normals, true_materials=True, normal_lr=1e-2, normal_prior_weight=0.0)
    assert rendered_error(scene_with_tilted_normals, turned.normals) < 0.6 * before, before
    assert torch.allclose(turned.normals.norm(dim=-1), torch.ones(len(truth)), atol=1e-5)
    kept = refine_tilted(
        scene_with_tilted_normals, start=truth, true_materials=True, normal_lr=1e-3, normal_prior_weight=0.0
    )
    assert rendered_error(scene_with_tilted_normals, kept.normals) < 0.5


def test_normals_stay_frozen_at_rate_zero_and_in_variants_without_the_pbr_loss(scene_with_tilted_normals):
    tilted = scene_with_tilted_normals[2]
    assert torch.equal(refine_tilted(scene_with_tilted_normals, iterations=20, normal_lr=0.0).normals, tilted)
    for variant in ("supervised", "proj-average"):
        result = refine_tilted(scene_with_tilted_normals, iterations=20, normal_lr=1e-2, variant=variant)
        assert torch.equal(result.normals, tilted)
    assert not RefineConfig(variant="supervised").refines_normals
    assert RefineConfig(variant="no-prior").refines_normals and RefineConfig(variant="no-softmax").refines_normals


def test_the_prior_holds_normals_at_the_geometrys_and_predicted_maps_pull_them_to_theirs(scene_with_tilted_normals):
    """A strong prior keeps them near the geometry's normals; the true normal maps given as the predicted ones pull
    the rendered normals there, where the photo loss alone, with the merger's imperfect materials, does not."""
    gaussians, truth, tilted, views = scene_with_tilted_normals[:4]
    held = refine_tilted(scene_with_tilted_normals, iterations=60, normal_lr=1e-2, normal_prior_weight=100.0)
    assert mean_error(held.normals, tilted) < 1.5
    free = refine_tilted(scene_with_tilted_normals, iterations=60, normal_lr=1e-2, normal_prior_weight=0.0)
    true_maps = []
    for view in views:  # the true normals, rendered: unit on the object, zero off it (no prediction there)
        gbuffer = render_gbuffer(Asset(gaussians, torch.zeros(len(gaussians), 5), truth), view.camera)
        true_maps.append(F.normalize(gbuffer.normals, dim=-1) * (gbuffer.alpha > 0.5)[..., None])
    settings = {"iterations": 60, "normal_lr": 1e-2, "normal_prior_weight": 0.0, "predicted_normal_weight": 1.0}
    pulled = refine_tilted(scene_with_tilted_normals, normal_maps=true_maps, **settings)
    assert rendered_error(scene_with_tilted_normals, pulled.normals) < 0.5 * rendered_error(
        scene_with_tilted_normals, free.normals
    )
    assert "predicted_normals" in pulled.history[-1] and "predicted_normals" not in free.history[-1]
    assert "normal_prior" in held.history[-1] and "normal_prior" not in free.history[-1]


def test_the_normal_map_loss_counts_only_object_pixels_with_a_prediction():
    rendered = torch.tensor([[[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]], [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    target = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]])
    mask = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    # pixels: aligned (0), flipped (0: no sign), at right angles (1), no prediction and off the mask (skipped)
    assert float(normal_map_loss(rendered, target, mask)) == pytest.approx(1.0 / 3.0)


def test_normal_settings_must_be_non_negative():
    with pytest.raises(SettingError, match="normal_lr"):
        RefineConfig(normal_lr=-1.0)
    with pytest.raises(SettingError, match="normal_prior_weight"):
        RefineConfig(normal_prior_weight=-0.1)
    with pytest.raises(SettingError, match="normal_neighbours"):
        RefineConfig(normal_neighbours=-1)


def test_nearest_neighbours_match_sorting_every_distance():
    points = torch.randn(300, 3, generator=torch.Generator().manual_seed(0))
    d2, index = nearest_neighbours(points, 7)
    full = torch.cdist(points, points).square().fill_diagonal_(float("inf"))
    want = torch.sort(full, dim=1)
    assert torch.allclose(d2, want.values[:, :7], atol=1e-5) and torch.equal(index, want.indices[:, :7])
    twice = torch.cat([points[:5], points[:5]])  # duplicates: each point's twin is its nearest, never itself
    d2, index = nearest_neighbours(twice, 1)
    assert torch.equal(index[:, 0], torch.tensor([5, 6, 7, 8, 9, 0, 1, 2, 3, 4])) and torch.all(d2 == 0)
    assert nearest_neighbours(points[:1], 4)[1].shape == (1, 0)


def test_smoothed_normals_match_a_loop_over_each_gaussians_neighbours():
    generator = torch.Generator().manual_seed(1)
    means, normals = (
        torch.randn(60, 3, generator=generator),
        F.normalize(torch.randn(60, 3, generator=generator), dim=-1),
    )
    weights = torch.rand(60, generator=generator)
    got = smoothed_normals(normals, means, weights, neighbours=5, agreement=2.0)
    for i in range(60):
        d2 = ((means - means[i]).square().sum(-1)).index_fill(0, torch.tensor([i]), float("inf"))
        near = torch.argsort(d2)[:5]
        scale = d2[near].mean()
        total = weights[i] * normals[i]
        for j in near:
            cos = float(normals[j] @ normals[i])
            total = total + weights[j] * torch.exp(-d2[j] / scale) * abs(cos) ** 2 * (1 if cos > 0 else -1) * normals[j]
        assert torch.allclose(got[i], F.normalize(total, dim=0), atol=1e-5)


def test_smoothing_takes_noise_off_a_plane_keeps_each_normals_sign_and_both_sides_of_a_crease():
    generator = torch.Generator().manual_seed(2)
    xy = torch.rand(2000, 2, generator=generator)
    up = torch.tensor([0.0, 0.0, 1.0])
    noisy = F.normalize(up + 0.3 * torch.randn(2000, 3, generator=generator), dim=-1)
    signs = torch.where(torch.rand(2000, generator=generator) < 0.5, -1.0, 1.0)[:, None]  # no sign: either way
    plane = torch.cat([xy, torch.zeros(2000, 1)], dim=1)
    smoothed = smoothed_normals(noisy * signs, plane, torch.ones(2000))
    assert mean_error(smoothed, up.expand(2000, 3)) < 0.5 * mean_error(noisy, up.expand(2000, 3))
    assert ((smoothed * noisy * signs).sum(-1) > 0).all()
    # a right-angled crease: the floor (normal +z) meets a wall (normal +x) along x = 0; exact normals stay exact
    wall = torch.cat([torch.zeros(2000, 1), xy], dim=1)
    crease = torch.cat([plane, wall])
    exact = torch.cat([up.expand(2000, 3), torch.tensor([1.0, 0.0, 0.0]).expand(2000, 3)])
    assert torch.allclose(smoothed_normals(exact, crease, torch.ones(4000)), exact, atol=1e-6)


def test_normal_neighbours_smooth_the_normals_every_variant_shades_with(scene_with_tilted_normals):
    truth, tilted = scene_with_tilted_normals[1], scene_with_tilted_normals[2]
    result = refine_tilted(scene_with_tilted_normals, iterations=0, variant="proj-average", normal_neighbours=16)
    assert mean_error(result.normals, truth) < mean_error(tilted, truth) - 5.0
    assert rendered_error(scene_with_tilted_normals, result.normals) < rendered_error(scene_with_tilted_normals, tilted)


def test_the_smoothed_normals_are_made_once_for_the_variants_of_one_run(scene_with_tilted_normals, monkeypatch):
    """Two variants refined from the same inputs (as a run's are) average the normals once, and shade with the
    same ones; without neighbours the geometry's normals are used as they are."""
    import matspray.method.refine.loop as loop

    gaussians, _, tilted, views, maps, lifted, _ = scene_with_tilted_normals
    inputs = RefineInputs(gaussians, tilted, lifted.values, lifted.seen, views, maps, BOUNDS)
    calls = []
    monkeypatch.setattr(loop, "smoothed_normals", lambda *args: calls.append(args) or smoothed_normals(*args))
    results = [
        refine(inputs, RefineConfig(iterations=0, normal_neighbours=16, variant=variant), progress=False)
        for variant in ("proj-average", "no-softmax")
    ]
    assert len(calls) == 1 and results[0].normals is results[1].normals
    assert torch.equal(results[0].normals, smoothed_normals(tilted, gaussians.means, gaussians.opacities, 16))
    unsmoothed = RefineConfig(iterations=0, variant="proj-average", normal_neighbours=0)
    assert refine(inputs, unsmoothed, progress=False).normals is tilted
    assert RefineConfig().normal_neighbours == 16  # on by default; `--method paper` switches it off (an addition)
