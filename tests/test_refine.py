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
