"""A refinement step's image-sized part as pure functions of tensors (`matspray.method.refine.terms`), run as CUDA
graphs on a CUDA device (`matspray.device.Graphed`; here through the stand-in of benchmarks.step_cost, which runs each
as one operation each way): the same terms and gradients as the deferred shading and losses op by op, and the same
refinement."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from benchmarks.step_cost import graph_stand_in, measure, refine_inputs
from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb
from matspray.device import Graphed, capturing_with
from matspray.errors import SettingError
from matspray.geometry.losses import normal_map_loss, photometric_loss
from matspray.material import unstack
from matspray.method.config import build_config, variant_refine_config
from matspray.method.refine.loop import RefineConfig, TrainingViews, refine, view_losses
from matspray.method.refine.terms import (
    TermOptions,
    light_images,
    material_loss,
    prefiltered_light,
    total_loss,
    view_terms,
    weighted_l1,
)
from matspray.render.backend import rendering_with, resolve_backend
from matspray.render.shade.brdf import camera_light_radiance
from matspray.render.shade.deferred import GBuffer, shade_gbuffer, view_directions
from matspray.render.shade.envmap import DEFAULT_LEVELS, EnvironmentMap
from matspray.render.shade.latlong import total_variation

# benchmarks.step_cost's count of the graphed path's operations per refinement step when this test was written (241),
# with about 10 % room
MAX_GRAPHED_OPERATIONS = 265


def view_inputs(height: int, width: int, seed: int, shadowed: bool, device="cpu"):
    """Random blended features, coverage, a view's constants and an environment map's log radiance."""
    g = torch.Generator().manual_seed(seed)
    camera = Camera.look_at([0.3, -3.0, 0.6], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, width, height)
    alpha = torch.rand(height, width, generator=g) * (torch.rand(height, width, generator=g) > 0.2)
    channels = 14 if shadowed else 8
    blended = (torch.rand(height, width, channels, generator=g) - 0.2) * alpha[..., None]
    surface = (torch.rand(height, width, generator=g) > 0.4).float() * (alpha > 0.5)
    weight = surface[..., None].expand(height, width, 5)
    predicted = torch.nn.functional.normalize(torch.randn(height, width, 3, generator=g), dim=-1)
    predicted = predicted * (torch.rand(height, width, 1, generator=g) > 0.3)  # zero: no prediction
    tensors = {
        "blended": blended.requires_grad_(True),
        "alpha": alpha,
        "cover": alpha.clamp_min(1e-6)[..., None],
        "view_dirs": view_directions(camera),
        "photo": torch.rand(height, width, 3, generator=g),
        "target": torch.rand(height, width, 5, generator=g),
        "surface": surface,
        "surface_weight": weight,
        "surface_count": weight.sum().clamp_min(1.0),
        "normal_map": predicted,
        "flash": torch.rand(height, width, 3, generator=g) * 2.0,  # a camera light's irradiance
    }
    log_map = (0.5 * torch.randn(8, 16, 3, generator=g)).requires_grad_(True)
    return camera, {k: v.to(device) for k, v in tensors.items()}, log_map.detach().to(device).requires_grad_(True)


def reference_terms(options: TermOptions, camera, t: dict, log_map) -> list[torch.Tensor]:
    """The terms as `refine.view_losses` computed them op by op before (commit 40c6e4b): the G-buffer of the blend,
    `shade_gbuffer` under `EnvironmentMap.prefilter`, the material and normal losses."""
    blended, alpha = t["blended"], t["alpha"]
    gbuffer = GBuffer.from_blended(blended, alpha)
    maps = gbuffer.materials
    terms = []
    if options.material == "l1":
        terms.append(weighted_l1(maps, t["target"], t["surface_weight"], t["surface_count"]))
    elif options.material is not None:
        terms.append(material_loss(maps, t["target"], t["surface"], options.material, options.huber_delta))
    if options.predicted_normals:
        terms.append(normal_map_loss(gbuffer.normals, t["normal_map"], t["surface"]))
    if options.photo:
        light = EnvironmentMap(log_map.detach()).prefilter()
        rendered = shade_gbuffer(gbuffer, camera, light, view_dirs=t["view_dirs"])
        if options.camera_light:
            flash = camera_light_radiance(*unstack(maps), gbuffer.normals, t["view_dirs"], t["flash"])
            rendered = rendered + flash * alpha[..., None]
        terms.append(photometric_loss(linear_to_srgb(rendered), t["photo"], options.ssim_weight))
    return terms


OPTIONS = [
    TermOptions("l1", 0.05, False, True, 0.2, False, DEFAULT_LEVELS),
    TermOptions("huber", 0.05, True, True, 0.2, True, DEFAULT_LEVELS),
    TermOptions("scale-invariant", 0.05, False, True, 0.3, False, DEFAULT_LEVELS),
    TermOptions(None, 0.05, False, True, 0.2, False, DEFAULT_LEVELS),  # the light warm-up
    TermOptions("l1", 0.05, True, False, 0.2, False),  # no light (supervised)
    TermOptions("l1", 0.05, False, True, 0.2, False, DEFAULT_LEVELS, camera_light=True),  # a flash at the camera
]


def graph_inputs(t: dict, light) -> tuple:
    keys = ("blended", "alpha", "cover", "view_dirs", "photo", "target", "surface", "surface_weight", "surface_count")
    return (*(t[k] for k in keys), t["normal_map"], t.get("flash", t["view_dirs"]), *light)


@pytest.mark.parametrize("options", OPTIONS)
def test_the_terms_are_the_deferred_shading_and_losses_op_by_op(options):
    camera, t, log_map = view_inputs(12, 14, 0, options.shadowed)
    light = light_images(EnvironmentMap(log_map.detach()).prefilter()) if options.photo else ()
    terms = view_terms(options, *graph_inputs(t, light))
    expected = reference_terms(options, camera, t, log_map)
    assert terms.shape == (len(options.names),) and len(expected) == len(options.names)
    # a flash is added before the coverage multiplies, in the reference after it: a rounding apart
    exact = {"rtol": 1e-6, "atol": 1e-7} if options.camera_light else {"rtol": 0, "atol": 0}
    torch.testing.assert_close(terms, torch.stack(expected), **exact)
    (gradient,) = torch.autograd.grad(terms.sum(), t["blended"])
    (expected_gradient,) = torch.autograd.grad(sum(expected), t["blended"])
    torch.testing.assert_close(gradient, expected_gradient, **exact)


def test_the_prefiltered_light_is_the_environment_maps():
    _, _, log_map = view_inputs(4, 4, 1, False)
    *images, radiance, prior = prefiltered_light(DEFAULT_LEVELS, log_map)
    expected = EnvironmentMap(log_map.detach()).prefilter()
    for got, want in zip(images, light_images(expected)):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    torch.testing.assert_close(radiance, log_map.exp(), rtol=0, atol=0)
    torch.testing.assert_close(prior, total_variation(log_map), rtol=0, atol=0)


@pytest.mark.parametrize("options", OPTIONS[:2] + OPTIONS[3:])
def test_graphed_terms_and_light_give_the_same_values_and_gradients(options):
    # through the stand-in: one capture per options and layout, replayed with new values after that
    with capturing_with(graph_stand_in):
        terms_of, light_of = Graphed(view_terms, "terms"), Graphed(prefiltered_light, "light")
    eager_terms, eager_light = Graphed(view_terms, "terms", graphs=False), Graphed(prefiltered_light, "light", False)

    def run(terms_function, light_function, t, log_map):
        light = ()
        if options.photo:
            *light, _, prior = light_function(DEFAULT_LEVELS, log_map)
        terms = terms_function(options, *graph_inputs(t, light))
        loss = terms.sum() + (0.3 * prior if options.photo else 0.0)
        wanted = [t["blended"], log_map] if options.photo else [t["blended"]]
        return terms.detach(), torch.autograd.grad(loss, wanted)

    for seed in (0, 1):
        _, t, log_map = view_inputs(12, 13, seed, options.shadowed)  # SSIM's window is 11 px
        expected, expected_gradients = run(eager_terms, eager_light, t, log_map)
        terms, gradients = run(terms_of, light_of, t, log_map)
        torch.testing.assert_close(terms, expected, rtol=0, atol=0)
        for got, want in zip(gradients, expected_gradients):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert len(terms_of.captured) == 1 and len(light_of.captured) == (1 if options.photo else 0)


def test_a_failed_capture_is_said_once_and_computed_op_by_op(capsys):
    def failing(function, samples):
        raise RuntimeError("operation not permitted when stream is capturing\nmore")

    with capturing_with(failing):
        terms_of = Graphed(view_terms, "refinement's loss terms")
    options = OPTIONS[4]
    for seed in (0, 1):
        _, t, _ = view_inputs(6, 8, seed, False)
        torch.testing.assert_close(terms_of(options, *graph_inputs(t, ())), view_terms(options, *graph_inputs(t, ())))
    assert terms_of.graphs is False
    said = capsys.readouterr().err.splitlines()
    assert said == [
        "refinement's loss terms runs without CUDA graphs (RuntimeError: operation not permitted when stream is "
        "capturing)"
    ]


def refined(inputs, config, graphs: bool, capture=None, **options):
    with capturing_with(capture):
        result = refine(inputs, config, progress=False, graphs=graphs, **options)
    log_map = None if result.envmap is None else result.envmap.log_map.detach()
    return result.materials, result.normals, log_map, result.history


@pytest.mark.parametrize("variant", ["full", "supervised"])
def test_refinement_with_graphed_terms_is_refinement_op_by_op(variant):
    base = build_config("paper").refine
    config = replace(base, iterations=8, light_warmup=3, log_every=4, variant=variant)
    with rendering_with("numba"):
        inputs = refine_inputs(torch.device("cpu"), points=300)
        eager = refined(inputs, config, graphs=False)
        graphed = refined(inputs, config, graphs=True, capture=graph_stand_in)
    for a, b in zip(graphed[:3], eager[:3]):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert graphed[3] == eager[3]


def test_refinement_with_a_known_light_and_graphed_terms_is_refinement_op_by_op():
    base = build_config("paper").refine
    config = replace(base, iterations=6, log_every=3)
    light = EnvironmentMap.constant([0.8, 0.6, 0.5], height=8, learnable=False)
    with rendering_with("numba"):
        inputs = refine_inputs(torch.device("cpu"), points=300)
        eager = refined(inputs, config, graphs=False, light=light)
        graphed = refined(inputs, config, graphs=True, capture=graph_stand_in, light=light)
    torch.testing.assert_close(graphed[0], eager[0], rtol=0, atol=0)
    assert graphed[3] == eager[3] and math.isfinite(eager[3][-1]["photo"])


@pytest.mark.slow  # two counted refinements: a few seconds each on an idle machine, a minute on a busy one
def test_a_graphed_refinement_step_stays_about_three_times_smaller():
    # benchmarks.step_cost, path gpu (what a CUDA device dispatches), the same steps counted with the terms and light
    # replayed as graphs (through the stand-in) and op by op: no host read, and about a third of the operations
    cpu = torch.device("cpu")
    graphed = measure("refine", "gpu", cpu, short=12, long=20)
    eager = measure("refine", "gpu", cpu, graphs=False, short=12, long=20)
    assert graphed["host_syncs"] == 0, graphed["sync_kinds"]
    assert graphed["operations"] <= MAX_GRAPHED_OPERATIONS, graphed["top_operations"]
    assert 2.7 * graphed["operations"] <= eager["operations"], (graphed["operations"], eager["operations"])


@pytest.mark.on_device
@pytest.mark.slow  # on the CPU its two captures trace through make_fx: 20 s against 7 s op by op on both sides
def test_graphed_terms_match_op_by_op_on_the_device(device):
    # on CUDA a view's terms and the light run as CUDA graphs: the same terms and gradients as op by op (up to the
    # rounding of gsplat's atomic sums, another order on every run), capture and replays; elsewhere through the
    # stand-in's replay (static buffers, the capture's Python), which is what `graphs=True` does off CUDA in tests
    config = build_config("paper").refine
    capture = None if device.type == "cuda" else graph_stand_in
    with rendering_with(resolve_backend("auto", device)), capturing_with(capture):
        inputs = refine_inputs(device, points=300)
        graphed, eager = TrainingViews(inputs), TrainingViews(inputs, graphs=False)
        g = torch.Generator().manual_seed(0)
        envmap = EnvironmentMap((0.3 * torch.randn(16, 32, 3, generator=g)).to(device))
        for index in (0, 1, 0):  # a capture, a replay of it for another view, and another
            materials = torch.rand(len(inputs.gaussians), 5, generator=g).to(device).requires_grad_(True)
            found = []
            for training in (graphed, eager):
                terms = view_losses(training, index, materials, inputs.normals, envmap, config)
                total = sum(terms.values())
                found.append(
                    (
                        torch.stack(list(terms.values())).detach(),
                        *torch.autograd.grad(total, [materials, envmap.log_map]),
                    )
                )
            for a, b in zip(*found):
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
    assert len(graphed.terms.captured) == len(graphed.lights[prefiltered_light].captured) == 1
    assert not eager.terms.captured


def test_the_photometric_weight_counts_against_the_2d_maps_loss_only():
    run = build_config("demo", **{"refine.photo_weight": 2.0, "refine.normal_prior_weight": 0.1})
    with_maps = {"material": torch.tensor(1.0), "photo": torch.tensor(3.0), "normal_prior": torch.tensor(1.0)}
    assert total_loss(with_maps, variant_refine_config(run, "full")).item() == pytest.approx(1.0 + 2.0 * 3.0 + 0.1)
    no_maps = {"photo": torch.tensor(3.0), "normal_prior": torch.tensor(1.0)}  # no-prior: no 2D maps to weigh against
    assert total_loss(no_maps, variant_refine_config(run, "no-prior")).item() == pytest.approx(3.0 + 0.1)


@pytest.mark.parametrize("quantile", [0.2, 0.5, 0.75])
@pytest.mark.parametrize("basecolor_loss", ["l1", "huber"])
def test_the_metallic_term_is_smallest_at_the_quantile_of_the_views_metallic(quantile, basecolor_loss):
    """Brute force: a constant metallic tried against seven views' maps; the summed loss is least at their quantile
    (with q = 0.5 the median, as plain L1)."""
    views = torch.tensor([0.0, 0.05, 0.1, 0.3, 0.6, 0.7, 0.9])  # each view's metallic, sorted
    mask = torch.ones(2, 3)
    targets = [torch.full((2, 3, 5), 0.4).index_fill(-1, torch.tensor([4]), float(v)) for v in views]
    candidates = torch.linspace(0.0, 1.0, 1001)

    def total(m: float) -> float:
        maps = torch.full((2, 3, 5), 0.4).index_fill(-1, torch.tensor([4]), m)
        return sum(float(material_loss(maps, t, mask, basecolor_loss, metallic_quantile=quantile)) for t in targets)

    losses = torch.tensor([total(float(m)) for m in candidates])
    best = candidates[losses <= losses.min() + 1e-6]  # the minimisers (an interval where q * 7 is whole)
    rank = quantile * len(views)  # the q-quantile: the smallest value with at least q of the views at or below it
    expected = views[math.ceil(rank) - 1]
    assert float(best.min()) <= float(expected) + 1e-3 and float(best.max()) >= float(expected) - 1e-3
    if quantile == 0.5:
        maps = torch.rand(2, 3, 5)
        plain = material_loss(maps, targets[2], mask, basecolor_loss)
        assert torch.equal(material_loss(maps, targets[2], mask, basecolor_loss, metallic_quantile=0.5), plain)


def test_the_graphed_l1_term_takes_the_metallic_quantile_as_the_material_loss_does():
    camera, t, log_map = view_inputs(6, 8, seed=3, shadowed=False)
    options = TermOptions("l1", 0.05, False, False, 0.2, False, metallic_quantile=0.25)
    maps = GBuffer.from_blended(t["blended"], t["alpha"]).materials
    (term,) = view_terms(options, *graph_inputs(t, ()))
    mask = t["surface"]
    reference = material_loss(maps, t["target"], mask, "l1", metallic_quantile=0.25)
    assert torch.allclose(term, reference, rtol=1e-5, atol=1e-7)
    assert not torch.allclose(term, material_loss(maps, t["target"], mask, "l1"))
    with pytest.raises(SettingError, match="metallic_quantile"):
        RefineConfig(metallic_quantile=1.0)


def test_refinement_takes_the_metallic_quantile_from_its_config():
    """A lower quantile leaves less metal where the views' maps disagree (free materials, the 2D maps' loss only)."""
    base = replace(build_config("paper").refine, iterations=30, log_every=10, variant="supervised")
    with rendering_with("numba"):
        inputs = refine_inputs(torch.device("cpu"), points=300)
        metallic = {q: refined(inputs, replace(base, metallic_quantile=q), graphs=False)[0][:, 4] for q in (0.1, 0.9)}
    assert float(metallic[0.1].mean()) < float(metallic[0.9].mean()) - 0.01
