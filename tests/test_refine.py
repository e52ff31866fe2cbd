import pytest
import torch

from matspray.errors import ConfigError
from matspray.lift import LiftConfig, lift
from matspray.merger import projection_average
from matspray.refine import VARIANTS, RefineConfig, refine, view_losses
from matspray.render.envmap import EnvironmentMap
from matspray.render.gbuffer import FrozenViews
from tests.scenes import material_scene

BOUNDS = torch.tensor([[-1.2] * 3, [1.2] * 3])


@pytest.fixture(scope="module")
def lifted_scene():
    gaussians, normals, materials, views, maps = material_scene()
    result = lift(gaussians, [v.camera for v in views], maps, [v.alpha for v in views], [v.name for v in views], LiftConfig(samples_per_side=2), progress=False)
    kept = gaussians.subset(result.kept)
    return kept, normals[result.kept], materials[result.kept], views, maps, result


def mean_losses(gaussians, normals, materials, envmap, views, maps, config):
    frozen = FrozenViews(gaussians, [v.camera for v in views])
    with torch.no_grad():
        terms = [view_losses(frozen, i, materials, normals, views[i], maps[i], envmap, config) for i in range(len(views))]
    return {name: sum(float(t[name]) for t in terms) / len(terms) for name in terms[0]}


def test_short_refinement_lowers_both_losses(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=40, envmap_height=8, seed=0)
    start_light = EnvironmentMap.constant(config.envmap_init, height=config.envmap_height)
    before = mean_losses(gaussians, normals, projection_average(lifted.values, lifted.seen), start_light, views, maps, config)
    result = refine(gaussians, normals, lifted.values, lifted.seen, views, maps, BOUNDS, config, progress=False)
    after = mean_losses(gaussians, normals, result.materials, result.envmap, views, maps, config)
    assert after["photo"] < 0.7 * before["photo"], (before, after)
    assert after["material"] < before["material"], (before, after)


@pytest.mark.parametrize("variant", VARIANTS)
def test_each_variant_runs(lifted_scene, variant):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=3, variant=variant, envmap_height=8)
    result = refine(gaussians, normals, lifted.values, lifted.seen, views, maps, BOUNDS, config, progress=False)
    assert result.materials.shape == (len(gaussians), 5)
    assert torch.isfinite(result.materials).all()
    assert (result.envmap is not None) == (variant in ("full", "no-softmax"))


def test_unknown_variant_is_refused():
    with pytest.raises(ConfigError, match="unknown variant 'best'.*full, proj-average, supervised, no-softmax"):
        RefineConfig(variant="best")


def test_supervised_materials_converge_to_the_2d_maps_in_a_short_run(lifted_scene):
    """The free per-Gaussian materials start grey; with their own learning rate 60 steps bring the
    rasterized maps most of the way to the 2D maps (at the merger's 1e-3 they would barely move)."""
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=60, variant="supervised", seed=0)
    grey = torch.full((len(gaussians), 5), 0.5)
    before = mean_losses(gaussians, normals, grey, None, views, maps, config)["material"]
    result = refine(gaussians, normals, lifted.values, lifted.seen, views, maps, BOUNDS, config, progress=False)
    after = mean_losses(gaussians, normals, result.materials, None, views, maps, config)["material"]
    assert after < 0.4 * before, (before, after)


def test_a_non_finite_gradient_stops_refinement_naming_the_step_and_parameter():
    from matspray.errors import NumericalError
    from matspray.refine import check_finite_gradients

    good, bad = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(3))
    good.grad, bad.grad = torch.ones(2), torch.tensor([0.0, float("nan"), 1.0])
    check_finite_gradients(7, [{"name": "environment map", "params": [good]}])
    with pytest.raises(NumericalError, match="refine step 7: non-finite gradient for the full materials"):
        check_finite_gradients(7, [{"name": "environment map", "params": [good]}, {"name": "full materials", "params": [good, bad]}])


def test_light_warm_up_fits_the_environment_map_and_leaves_the_merger_at_its_start(lifted_scene):
    """Warm-up steps train only the light: with no merger steps after it the materials are still the
    projection average, and the photo loss is lower than with the initial constant map."""
    from matspray.refine import warm_up_light

    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(envmap_height=8, light_warmup=30)
    average = projection_average(lifted.values, lifted.seen)
    light = EnvironmentMap.constant(config.envmap_init, height=config.envmap_height)
    before = mean_losses(gaussians, normals, average, light, views, maps, config)["photo"]
    frozen = FrozenViews(gaussians, [v.camera for v in views])
    warm_up_light(frozen, average, light, normals, views, config, torch.Generator().manual_seed(0), None, progress=False)
    after = mean_losses(gaussians, normals, average, light, views, maps, config)["photo"]
    assert after < 0.8 * before, (before, after)


def test_min_coverage_runs_the_merger_on_fewer_gaussians_with_a_close_result(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    frozen = FrozenViews(gaussians, [v.camera for v in views])
    visible = frozen.visible_ids[0]
    assert torch.equal(frozen.contributing_ids(0, 0.0), visible)
    covering = frozen.contributing_ids(0, 0.05)
    assert 0 < len(covering) < len(visible)
    assert (frozen.coverage[0][covering] >= 0.05).all()
    results = {}
    for min_coverage in (0.0, 0.05):
        config = RefineConfig(iterations=20, envmap_height=8, seed=0, min_coverage=min_coverage)
        results[min_coverage] = refine(gaussians, normals, lifted.values, lifted.seen, views, maps, BOUNDS, config, progress=False).materials
    assert (results[0.0] - results[0.05]).abs().mean() < 0.01
