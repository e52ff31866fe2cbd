"""The spherical-Gaussian light (`render.shade.sg`): its lookups against brute-force quadrature, gradients, its files,
and refinement learning it through the light interface."""

import math

import pytest
import torch
import torch.nn.functional as F

from matspray.errors import DataError, SettingError
from matspray.method.refine.loop import RefineConfig, RefineInputs, refine
from matspray.render.shade.brdf import ggx_ndf, roughness_to_alpha, smith_visibility
from matspray.render.shade.deferred import shade
from matspray.render.shade.envmap import EnvironmentMap, prefilter_latlong
from matspray.render.shade.latlong import pixel_directions, pixel_solid_angles
from matspray.render.shade.models import load_light
from matspray.render.shade.sg import SGLight, lobes_path, sg_step
from tests.scenes import lift_material_scene, material_scene

ROWS = 256  # the quadrature grid: ROWS x 2 ROWS directions
BOUNDS = torch.tensor([[-1.2] * 3, [1.2] * 3])


def random_light(dtype=torch.float64, count=5) -> SGLight:
    g = torch.Generator().manual_seed(3)
    axes = torch.randn(count, 3, generator=g, dtype=dtype)
    sharpness = torch.tensor([1.0, 5.0, 30.0, 120.0, 0.3], dtype=dtype)[:count]
    return SGLight(axes, sharpness, torch.rand(count, 3, generator=g, dtype=dtype) + 0.1, height=8)


def quadrature_grid():
    directions = pixel_directions(ROWS, 2 * ROWS, dtype=torch.float64).reshape(-1, 3)
    return directions, pixel_solid_angles(ROWS, 2 * ROWS, dtype=torch.float64).reshape(-1)


def unit_vectors(count: int, seed: int = 0) -> torch.Tensor:
    return F.normalize(
        torch.randn(count, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64), dim=-1
    )


def test_irradiance_matches_quadrature():
    light = random_light()
    directions, solid_angles = quadrature_grid()
    radiance = light.radiance(directions).detach()  # [D, 3]
    normals = unit_vectors(24)
    expected = ((normals @ directions.T).clamp_min(0.0) * solid_angles) @ radiance  # sum L (n.l)+ dw
    got = light.prefilter().lookup_diffuse(normals).detach()
    torch.testing.assert_close(got, expected, rtol=2e-3, atol=0.0)


@pytest.mark.parametrize("roughness", [0.2, 0.5, 1.0])
def test_specular_matches_the_split_sum_lobe_by_quadrature(roughness):
    # the split-sum definition (as `prefilter_latlong` convolves a map): sum L(l) w(l) / sum w(l), w = D V (r.l)+,
    # n = v = r. The SG stands in for the GGX lobe with the same mean cosine: measured at most 4.9 % off
    light = random_light()
    directions, solid_angles = quadrature_grid()
    radiance = light.radiance(directions).detach()
    lobe = unit_vectors(24, seed=1)
    cos = lobe @ directions.T
    alpha = roughness_to_alpha(torch.tensor(roughness, dtype=torch.float64))
    weights = ggx_ndf(((1 + cos) / 2).clamp_min(0).sqrt(), alpha) * smith_visibility(cos, torch.ones_like(cos), alpha)
    weights = weights * cos.clamp_min(0.0) * solid_angles
    expected = (weights @ radiance) / weights.sum(-1, keepdim=True)
    got = light.prefilter().lookup_specular(lobe, torch.full((24,), roughness, dtype=torch.float64)).detach()
    error = (got - expected).abs() / expected
    assert error.max() < 0.06 and error.mean() < 0.015, (float(error.max()), float(error.mean()))


def test_shading_reads_an_sg_light_as_the_lat_long_map_of_its_radiance():
    # the same light through both models: a sharp-lobed SG drawn on a fine lat-long map and prefiltered; shading
    # through the interface agrees within the two approximations' errors
    light = random_light(torch.float32, count=4)
    drawn = light.radiance(pixel_directions(32, 64)).detach()
    g = torch.Generator().manual_seed(2)
    base, rough, metal = (
        torch.rand(64, 3, generator=g),
        0.3 + 0.7 * torch.rand(64, generator=g),
        torch.rand(64, generator=g),
    )
    normals, views = unit_vectors(64, 4).float(), unit_vectors(64, 5).float()
    views = torch.where((normals * views).sum(-1, keepdim=True) < 0, -views, views)
    by_sg = shade(base, rough, metal, normals, views, light)
    by_map = shade(base, rough, metal, normals, views, prefilter_latlong(drawn))
    assert ((by_sg - by_map).abs() / by_map).median() < 0.03


def test_gradients_of_the_lookups_and_prior_match_finite_differences():
    light = random_light(count=3)
    directions, roughness, normals = (
        unit_vectors(4, 6),
        torch.tensor([0.3, 0.5, 0.8, 1.0], dtype=torch.float64),
        unit_vectors(4, 7),
    )
    _, layout, (_, _, _, *constants) = light.step_function((0.2, 0.6, 1.0))

    def outputs(vectors, log_sharpness, log_amplitudes):
        *tensors, drawn, prior = sg_step(layout, vectors, log_sharpness, log_amplitudes, *constants)
        pre = light.prefiltered_type.from_tensors(layout, tensors)
        specular, diffuse = pre.lookup(directions, roughness, normals)
        return specular, diffuse, drawn.sum(), prior

    parameters = [p.detach().clone().requires_grad_(True) for p in light.parameters()]
    assert torch.autograd.gradcheck(outputs, parameters, eps=1e-6, atol=1e-5)


def test_save_and_load_round_trip(tmp_path):
    light = random_light(torch.float32)
    path = tmp_path / "envmap.exr"
    light.save(path)
    loaded = load_light(path)
    assert isinstance(loaded, SGLight) and not loaded.learnable and loaded.height == light.height
    for got, want in zip(loaded.lobes, light.lobes):
        torch.testing.assert_close(got, want.detach(), rtol=1e-6, atol=1e-7)
    # every reader of an asset's light reads the drawing as a lat-long map
    torch.testing.assert_close(EnvironmentMap.from_file(path).map, light.map.detach(), rtol=1e-3, atol=1e-4)
    plain = tmp_path / "plain" / "envmap.exr"
    plain.parent.mkdir()
    EnvironmentMap.constant(0.5, 4).save(plain)
    assert isinstance(load_light(plain), EnvironmentMap)


def test_a_fixed_copy_is_the_same_light_without_gradients():
    light = random_light(torch.float32)
    fixed = light.fixed()
    assert light.learnable and not fixed.learnable
    for got, want in zip(fixed.parameters(), light.parameters()):
        assert torch.equal(got, want)


def test_a_broken_lobes_file_is_one_line_naming_it(tmp_path):
    path = tmp_path / "envmap.exr"
    random_light(torch.float32).save(path)
    lobes_path(path).write_text('{"axes": [[0, 0, 1]], "sharpness": [-1], "amplitudes": [[1, 1, 1]], "height": 4}')
    with pytest.raises(DataError) as error:
        load_light(path)
    message = str(error.value)
    assert message.startswith(str(lobes_path(path))) and "\n" not in message and "sharpness" in message


def test_the_initial_light_has_the_mean_radiance_asked_for():
    light = SGLight.initial(0.5, height=8)
    assert len(light.vectors) == 16 and light.learnable
    directions, solid_angles = quadrature_grid()
    mean = (light.radiance(directions.float()).detach() * solid_angles[:, None].float()).sum(0) / (4 * math.pi)
    torch.testing.assert_close(mean, torch.full((3,), 0.5), rtol=1e-3, atol=0.0)


def test_an_unknown_light_model_is_refused():
    with pytest.raises(SettingError, match="light_model.*unknown model 'probe'.*latlong, sg"):
        RefineConfig(light_model="probe")


def test_refinement_learns_an_sg_light():
    gaussians, normals, _, views, maps = material_scene()
    lifted = lift_material_scene(gaussians, views, maps)
    kept = gaussians.subset(lifted.kept)
    inputs = RefineInputs(
        kept, normals[lifted.kept], lifted.values, lifted.seen, views, maps, torch.tensor([[-1.2] * 3, [1.2] * 3])
    )
    config = RefineConfig(iterations=30, envmap_height=4, light_warmup=10, light_model="sg", log_every=1)
    result = refine(inputs, config, progress=False)
    assert isinstance(result.envmap, SGLight) and len(result.envmap.vectors) == 8
    start = SGLight.initial(config.envmap_init, config.envmap_height)
    assert not torch.equal(result.envmap.log_amplitudes.detach(), start.log_amplitudes.detach())  # it was learned
    photo = [record["photo"] for record in result.history]
    assert photo[-1] < 0.8 * photo[0], photo


def test_refinement_with_an_sg_light_runs_as_graphs_with_the_same_results(capsys):
    # through the graph stand-in (static buffers replayed), as on a CUDA device: the SG light's prefiltering and the
    # terms that read it give what op by op gives
    from benchmarks.graph_replay import graph_stand_in
    from matspray.device import capturing_with

    gaussians, normals, _, views, maps = material_scene()
    lifted = lift_material_scene(gaussians, views, maps)
    inputs = RefineInputs(
        gaussians.subset(lifted.kept), normals[lifted.kept], lifted.values, lifted.seen, views, maps, BOUNDS
    )
    config = RefineConfig(iterations=6, envmap_height=4, light_warmup=2, light_model="sg", log_every=1)
    results = []
    for graphs in (True, False):
        with capturing_with(graph_stand_in):
            results.append(refine(inputs, config, progress=False, graphs=graphs))
    (graphed, eager) = results
    assert "without CUDA graphs" not in capsys.readouterr().err  # captured, not fallen back to op by op
    assert [r["photo"] for r in graphed.history] == [r["photo"] for r in eager.history]
    for got, want in zip(graphed.envmap.parameters(), eager.envmap.parameters()):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
