import math

import pytest
import torch

from matspray.errors import ConfigError
from matspray.method.merger import projection_average, view_gains
from matspray.method.refine.loop import (
    RefineConfig,
    RefineInputs,
    TrainingViews,
    aligned_inputs,
    masked_l1,
    material_loss,
    refine,
    scale_invariant_l1,
    spread_loss,
    view_losses,
    warm_up_light,
)
from matspray.presets import VARIANT_NAMES
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.envmap import EnvironmentMap
from tests.scenes import lift_material_scene, material_scene

BOUNDS = torch.tensor([[-1.2] * 3, [1.2] * 3])


@pytest.fixture(scope="module")
def lifted_scene():
    gaussians, normals, materials, views, maps = material_scene()
    result = lift_material_scene(gaussians, views, maps)
    kept = gaussians.subset(result.kept)
    return kept, normals[result.kept], materials[result.kept], views, maps, result


def refine_inputs(gaussians, normals, lifted, views, maps, visibility=None) -> RefineInputs:
    return RefineInputs(gaussians, normals, lifted.values, lifted.seen, views, maps, BOUNDS, visibility)


def mean_losses(gaussians, normals, materials, envmap, views, maps, config):
    training = TrainingViews(
        RefineInputs(
            gaussians,
            normals,
            torch.zeros(len(gaussians), len(views), 5),
            torch.ones(len(gaussians), len(views), dtype=torch.bool),
            views,
            maps,
            BOUNDS,
        )
    )
    with torch.no_grad():
        terms = [view_losses(training, i, materials, normals, envmap, config) for i in range(len(views))]
    return {name: sum(float(t[name]) for t in terms) / len(terms) for name in terms[0]}


def test_short_refinement_lowers_both_losses(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=40, envmap_height=8, seed=0, light_warmup=0)
    start_light = EnvironmentMap.constant(config.envmap_init, height=config.envmap_height)
    before = mean_losses(
        gaussians, normals, projection_average(lifted.values, lifted.seen), start_light, views, maps, config
    )
    result = refine(refine_inputs(gaussians, normals, lifted, views, maps), config, progress=False)
    after = mean_losses(gaussians, normals, result.materials, result.envmap, views, maps, config)
    assert after["photo"] < 0.7 * before["photo"], (before, after)
    assert after["material"] < before["material"], (before, after)


@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_each_variant_runs(lifted_scene, variant):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=3, variant=variant, envmap_height=8, light_warmup=0)
    result = refine(refine_inputs(gaussians, normals, lifted, views, maps), config, progress=False)
    assert result.materials.shape == (len(gaussians), 5)
    assert torch.isfinite(result.materials).all()
    assert (result.envmap is not None) == (variant in ("full", "no-softmax", "no-prior", "photos-only"))


def test_unknown_variant_is_refused():
    with pytest.raises(ConfigError, match="unknown variant 'best'.*full, proj-average, supervised, no-softmax"):
        RefineConfig(variant="best")


def test_scale_invariant_l1_ignores_a_global_scale_and_matches_a_brute_force_scale():
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(6, 5, 3, generator=generator) * 0.8 + 0.1
    mask = torch.rand(6, 5, generator=generator) > 0.3
    assert float(scale_invariant_l1(0.5 * target, target, mask.float())) == pytest.approx(0.0, abs=1e-6)
    pred = target * (1.0 + 0.3 * torch.rand(6, 5, 3, generator=generator))
    # least-squares scale over the masked pixels only, then the masked L1 at that scale
    weight = mask[..., None].float().expand_as(pred)
    scale = float((pred * target * weight).sum() / (pred * pred * weight).sum())
    expected = float(((scale * pred - target).abs() * weight).sum() / weight.sum())
    assert float(scale_invariant_l1(pred, target, mask.float())) == pytest.approx(expected, rel=1e-5)
    assert float(scale_invariant_l1(pred, target, mask.float())) < float(masked_l1(pred, target, mask.float()))


def test_material_loss_is_plain_l1_unless_the_base_color_is_scale_invariant():
    generator = torch.Generator().manual_seed(1)
    target = torch.rand(4, 4, 5, generator=generator)
    mask = torch.ones(4, 4)
    darker = torch.cat([0.5 * target[..., :3], target[..., 3:]], dim=-1)  # base color half as bright, the rest exact
    assert float(material_loss(darker, target, mask, "l1")) == pytest.approx(float(masked_l1(darker, target, mask)))
    assert float(material_loss(darker, target, mask, "scale-invariant")) == pytest.approx(0.0, abs=1e-6)
    rough = target.clone()
    rough[..., 3] += 0.2  # a roughness error is not forgiven: 0.2 on one channel of five
    assert float(material_loss(rough, target, mask, "scale-invariant")) == pytest.approx(0.2 / 5, rel=1e-5)


def test_the_huber_base_color_loss_is_quadratic_below_delta_and_l1_above():
    target = torch.rand(5, 6, 5, generator=torch.Generator().manual_seed(3))
    mask = (torch.arange(30).reshape(5, 6) % 3 != 0).float()  # a third of the pixels do not count
    for offset, per_pixel in ((0.02, 0.02**2 / (2 * 0.05)), (0.3, 0.3 - 0.05 / 2)):
        maps = target.clone()
        maps[..., :3] += offset
        maps[0, 0, :3] += 5.0  # masked out: changes nothing
        assert float(material_loss(maps, target, mask, "huber", 0.05)) == pytest.approx(3 * per_pixel / 5, rel=1e-5)


def test_across_views_the_huber_base_color_averages_close_views_and_outvotes_a_far_one():
    """The merger's material loss sums over the views a Gaussian is seen in; its minimiser over one base-colour value is
    what the loss makes of disagreeing views: L1 takes their median, Huber their mean while they agree to within delta
    and stays near the others when one view is far off."""

    def minimiser(values, loss, delta=0.05):
        def maps(base):  # [1, 1, 5]: grey base colour `base`, roughness and metallic as in every view
            return torch.tensor([[[base, base, base, 0.5, 0.0]]])

        grid = torch.linspace(0.0, 1.0, 20001)
        mask = torch.ones(1, 1)

        def total(x):
            return sum(material_loss(maps(float(x)), maps(v), mask, loss, delta) for v in values)

        coarse = float(grid[::20][torch.stack([total(x) for x in grid[::20]]).argmin()])
        fine = grid[(grid - coarse).abs() <= 1e-3]
        return float(fine[torch.stack([total(x) for x in fine]).argmin()])

    close = [0.30, 0.31, 0.33, 0.36, 0.38]  # within delta of their mean 0.336
    assert minimiser(close, "huber") == pytest.approx(sum(close) / 5, abs=2e-4)
    assert minimiser(close, "l1") == pytest.approx(0.33, abs=2e-4)  # the median
    outlier = [0.30, 0.32, 0.34, 0.36, 0.90]  # one view far off: the mean would be 0.444
    # four views in the quadratic part pull (4 x - 1.32) / 0.05, the far one pulls back by L1's slope 1
    assert minimiser(outlier, "huber") == pytest.approx((1.32 + 0.05) / 4, abs=2e-4)


def test_the_huber_delta_must_be_positive():
    with pytest.raises(ConfigError, match="basecolor_huber_delta: must be > 0, got 0"):
        RefineConfig(basecolor_loss="huber", basecolor_huber_delta=0.0)


def test_unknown_basecolor_loss_is_refused():
    with pytest.raises(ConfigError, match="basecolor_loss: unknown loss 'l2'.*l1, scale-invariant, huber"):
        RefineConfig(basecolor_loss="l2")


def test_negative_loss_weights_are_refused():
    with pytest.raises(ConfigError, match="photo_weight: must be >= 0, got -1"):
        RefineConfig(photo_weight=-1)


def test_the_base_color_is_compared_scale_invariantly_only_with_the_photometric_loss(lifted_scene):
    """Without an environment map (the supervised variant) nothing else would set the base color's
    brightness, so its material loss stays plain L1 whatever `basecolor_loss` says."""
    gaussians, normals, materials, views, maps, _ = lifted_scene
    darker = torch.cat([0.6 * materials[:, :3], materials[:, 3:]], dim=-1)
    light = EnvironmentMap.constant(0.5, height=8)
    plain = mean_losses(gaussians, normals, darker, None, views, maps, RefineConfig(basecolor_loss="scale-invariant"))
    assert plain["material"] == pytest.approx(
        mean_losses(gaussians, normals, darker, None, views, maps, RefineConfig(basecolor_loss="l1"))["material"]
    )
    lit = mean_losses(gaussians, normals, darker, light, views, maps, RefineConfig(basecolor_loss="scale-invariant"))
    assert lit["material"] < 0.8 * plain["material"], (lit, plain)


def test_supervised_materials_converge_to_the_2d_maps_in_a_short_run(lifted_scene):
    """The free per-Gaussian materials start grey; with their own learning rate 60 steps bring the
    rasterized maps most of the way to the 2D maps (at the merger's 1e-3 they would barely move)."""
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(iterations=60, variant="supervised", seed=0, light_warmup=0)
    grey = torch.full((len(gaussians), 5), 0.5)
    before = mean_losses(gaussians, normals, grey, None, views, maps, config)["material"]
    result = refine(refine_inputs(gaussians, normals, lifted, views, maps), config, progress=False)
    after = mean_losses(gaussians, normals, result.materials, None, views, maps, config)["material"]
    assert after < 0.4 * before, (before, after)


def test_a_non_finite_gradient_stops_refinement_naming_the_step_and_parameter():
    from matspray.errors import NumericalError
    from matspray.method.refine.loop import check_finite_gradients

    good, bad = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(3))
    good.grad, bad.grad = torch.ones(2), torch.tensor([0.0, float("nan"), 1.0])
    check_finite_gradients(7, [{"name": "environment map", "params": [good]}])
    with pytest.raises(NumericalError, match="refine step 7: non-finite gradient for the full materials"):
        check_finite_gradients(
            7, [{"name": "environment map", "params": [good]}, {"name": "full materials", "params": [good, bad]}]
        )


def test_light_warm_up_fits_the_environment_map_and_leaves_the_merger_at_its_start(lifted_scene):
    """Warm-up steps train only the light: with no merger steps after it the materials are still the
    projection average, and the photo loss is lower than with the initial constant map."""
    gaussians, normals, _, views, maps, lifted = lifted_scene
    config = RefineConfig(envmap_height=8, light_warmup=30)
    average = projection_average(lifted.values, lifted.seen)
    light = EnvironmentMap.constant(config.envmap_init, height=config.envmap_height)
    before = mean_losses(gaussians, normals, average, light, views, maps, config)["photo"]
    training = TrainingViews(refine_inputs(gaussians, normals, lifted, views, maps))
    warm_up_light(training, average, normals, light, config, torch.Generator().manual_seed(0), progress=False)
    after = mean_losses(gaussians, normals, average, light, views, maps, config)["photo"]
    assert after < 0.8 * before, (before, after)


def test_min_coverage_runs_the_merger_on_fewer_gaussians_with_a_close_result(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    frozen = FrozenViews(gaussians, [v.camera for v in views])
    visible = frozen.visible_ids[0]
    assert torch.equal(frozen.contributing_ids(0, 0.0), visible)
    default = RefineConfig().min_coverage  # the threshold a run uses
    covering = frozen.contributing_ids(0, default)
    assert 0 < len(covering) < len(visible)
    assert (frozen.coverage[0][covering] >= default).all()
    results = {}
    for min_coverage in (0.0, default):
        config = RefineConfig(iterations=20, envmap_height=8, seed=0, min_coverage=min_coverage, light_warmup=0)
        results[min_coverage] = refine(
            refine_inputs(gaussians, normals, lifted, views, maps), config, progress=False
        ).materials
    assert (results[0.0] - results[default]).abs().mean() < 0.01


def test_spread_loss_is_zero_for_equal_weights_and_log_n_for_one_view():
    seen = torch.tensor([[True, True, True, True], [True, True, False, False]])
    equal = seen.float() / seen.sum(-1, keepdim=True)
    assert float(spread_loss(equal, seen)) == pytest.approx(0.0, abs=1e-6)
    one = torch.tensor([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    assert float(spread_loss(one, seen)) == pytest.approx((math.log(4) + math.log(2)) / 2, rel=1e-5)
    w = torch.tensor([[0.7, 0.1, 0.1, 0.1]])  # against a brute-force KL divergence from 1/4 each
    assert float(spread_loss(w, seen[:1])) == pytest.approx(float((w * (w * 4).log()).sum()), rel=1e-5)


def test_the_spread_weight_keeps_the_base_colour_merger_near_the_average(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    inputs = refine_inputs(gaussians, normals, lifted, views, maps)
    average = projection_average(lifted.values, lifted.seen)

    def base_colour_change(weight):
        config = RefineConfig(iterations=40, envmap_height=8, seed=0, light_warmup=0, basecolor_spread_weight=weight)
        result = refine(inputs, config, progress=False)
        assert ("spread" in result.history[-1]) == (weight > 0)
        return float((result.materials[:, :3] - average[:, :3]).abs().mean()), float(
            (result.materials[:, 3:] - average[:, 3:]).abs().mean()
        )

    (free_base, free_rest), (held_base, held_rest) = base_colour_change(0.0), base_colour_change(1.0)
    assert held_base < 0.5 * free_base, (free_base, held_base)
    assert held_rest > 0.5 * free_rest  # roughness and metallic are left to the losses


def test_aligned_inputs_divide_each_views_lifted_values_and_2d_map_by_one_gain(lifted_scene):
    """The wiring: values and 2D maps of a view are divided by the gain `view_gains` finds for it (its estimate is
    tested in test_merger on a scene with dense overlap between views)."""
    gaussians, normals, _, views, maps, lifted = lifted_scene
    scaled = [
        torch.cat([(m[..., :3] * 0.7).clamp(0, 1), m[..., 3:]], dim=-1) if i == 1 else m for i, m in enumerate(maps)
    ]
    values = lifted.values.clone()
    values[:, 1, :3] *= 0.7  # view 1 is a darker batch, in its 2D map and so in what it lifted
    darker = RefineInputs(gaussians, normals, values, lifted.seen, views, scaled, BOUNDS)
    aligned, gains = aligned_inputs(darker), view_gains(darker.values, darker.seen)
    assert not torch.allclose(gains, torch.ones_like(gains))
    assert torch.allclose(aligned.values[..., :3], (values[..., :3] / gains).clamp(0, 1))
    assert torch.equal(aligned.values[..., 3:], values[..., 3:])
    for view in range(len(views)):
        assert torch.allclose(aligned.targets[view][..., :3], (scaled[view][..., :3] / gains[view]).clamp(0, 1))
        assert torch.equal(aligned.targets[view][..., 3:], scaled[view][..., 3:])


def test_a_known_light_is_used_as_given_and_sets_the_base_colours_brightness(lifted_scene):
    """With the true light fixed, the photos set the base colour's brightness: from maps 40% too dark in every view,
    the unconstrained merger (no-softmax) ends within 10% of the true mean, the softmax merger moves toward the
    brightest views; the light itself never changes (no warm-up, no optimisation)."""
    from tests.scenes import sky_map

    gaussians, normals, materials, views, maps, lifted = lifted_scene
    dark = [torch.cat([m[..., :3] * 0.6, m[..., 3:]], dim=-1) for m in maps]
    values = torch.cat([lifted.values[..., :3] * 0.6, lifted.values[..., 3:]], dim=-1)
    inputs = RefineInputs(gaussians, normals, values, lifted.seen, views, dark, BOUNDS)
    known = EnvironmentMap.from_tensor(sky_map(), height=8, learnable=False)
    average, truth = projection_average(values, lifted.seen)[:, :3].mean(), materials[:, :3].mean()
    for variant in ("full", "no-softmax"):
        config = RefineConfig(
            variant=variant,
            iterations=60,
            envmap_height=8,
            light_warmup=30,
            material_weight=0.0,
            merger_lr=1e-2,
            seed=0,
        )
        result = refine(inputs, config, progress=False, light=known)
        assert torch.equal(result.envmap.map, known.map)
        assert not any(p.requires_grad for p in result.envmap.parameters())
        brightness = result.materials[:, :3].mean()
        if variant == "full":
            assert brightness > average + 0.005, (float(brightness), float(average))
        else:
            assert abs(brightness / truth - 1.0) < 0.1, (float(brightness), float(truth))


def test_merger_coverage_counts_the_gaussians_the_merger_runs_for(lifted_scene):
    from benchmarks.merger_coverage import covered_counts

    gaussians, _, _, views, _, _ = lifted_scene
    frozen = FrozenViews(gaussians, [v.camera for v in views])
    counts = covered_counts(frozen, [0.0, 0.05, 0.5], views=len(views))
    visible = sum(len(ids) for ids in frozen.visible_ids) / len(views)
    assert counts[0.0] == pytest.approx(visible)
    by_hand = sum(int((frozen.coverage[i][frozen.visible_ids[i]] >= 0.05).sum()) for i in range(len(views)))
    assert counts[0.05] == pytest.approx(by_hand / len(views))
    assert counts[0.0] >= counts[0.05] >= counts[0.5]


def test_the_metallic_prior_pulls_photos_only_towards_a_dielectric_and_leaves_the_others(lifted_scene):
    gaussians, normals, _, views, maps, lifted = lifted_scene
    inputs = refine_inputs(gaussians, normals, lifted, views, maps)

    def metallic(variant: str, weight: float, start: float = 0.5, iterations: int = 30) -> torch.Tensor:  # -> [N]
        config = RefineConfig(
            iterations=iterations,
            variant=variant,
            envmap_height=8,
            light_warmup=0,
            seed=0,
            metallic_prior_weight=weight,
            metallic_prior_start=start,
        )
        return refine(inputs, config, progress=False).materials[:, 4]

    # both settings are used by photos-only: it starts where told, and from the same start the pull lowers it
    assert torch.allclose(metallic("photos-only", 0.0, 0.2, iterations=0), torch.full((len(gaussians),), 0.2))
    pulled, free = metallic("photos-only", 0.3), metallic("photos-only", 0.0)
    assert float(pulled.mean()) < float(free.mean()) - 0.02, (float(pulled.mean()), float(free.mean()))
    # and they are all it differs by: with both off it is no-prior, bit for bit
    assert torch.equal(free, metallic("no-prior", 0.0))
    for variant in ("no-prior", "full"):  # the others never read them (full: the 2D maps say what is metal there)
        assert torch.equal(metallic(variant, 0.3, 0.1), metallic(variant, 0.0, 0.5)), variant
    with pytest.raises(Exception, match="metallic_prior_weight: must be >= 0"):
        RefineConfig(metallic_prior_weight=-1.0)
    with pytest.raises(Exception, match=r"metallic_prior_start: must be in \(0, 1\), got 0.0"):
        RefineConfig(metallic_prior_start=0.0)


@pytest.mark.parametrize(
    "variant, kind, rate",
    [("full", "MergerSource", 1e-3), ("supervised", "FreeSource", 5e-2), ("proj-average", "AverageSource", 1e-3)],
)
def test_each_variant_declares_its_source_class_and_its_rate(lifted_scene, variant, kind, rate):
    from matspray.method.refine.sources import material_source
    from matspray.presets import get_variant

    gaussians, _, _, _, _, lifted = lifted_scene
    source = material_source(
        get_variant(variant), gaussians.means, lifted.values, lifted.seen, BOUNDS, RefineConfig().merger
    )
    assert type(source).__name__ == kind and source.trainable == (variant != "proj-average")
    assert source.learning_rate(RefineConfig(merger_lr=1e-3, supervised_lr=5e-2)) == rate
    assert source().shape == (len(gaussians), 5) and source(torch.tensor([0, 2])).shape == (2, 5)
