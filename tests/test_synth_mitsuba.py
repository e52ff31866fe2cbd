"""The Mitsuba side of `matspray synth`: light and camera conventions, a furnace check of the colour
handling, and ground-truth casts against analytic references on a sphere."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")

from matspray.data.camera import Camera  # noqa: E402
from matspray.data.images import read_image  # noqa: E402
from matspray.render.shade.lights import lookup_envmap  # noqa: E402
from matspray.synth.groundtruth import cast_ground_truth  # noqa: E402
from matspray.synth.materials import Textures, bake_textures, bilinear_lookup, random_material  # noqa: E402
from matspray.synth.mitsuba_scene import (  # noqa: E402
    build_scene,
    envmap_emitter,
    mitsuba_envmap_rows,
    render_view,
    sampler_for,
    select_variant,
)
from matspray.synth.shapes import sphere  # noqa: E402
from matspray.synth.writer import write_render  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def variant():
    return select_variant()


def uniform_textures(base_color, roughness: float, metallic: float, size: int = 4) -> Textures:
    return Textures(
        np.broadcast_to(np.asarray(base_color, np.float32), (size, 2 * size, 3)).copy(),
        np.full((size, 2 * size), roughness, np.float32),
        np.full((size, 2 * size), metallic, np.float32),
    )


def test_envmap_rows_for_mitsuba_keep_centres_and_midpoints():
    env = np.arange(4 * 8 * 3, dtype=np.float32).reshape(4, 8, 3)
    rows = mitsuba_envmap_rows(env)
    assert rows.shape == (9, 8, 3)
    np.testing.assert_array_equal(rows[1::2], env)
    np.testing.assert_allclose(rows[4], 0.5 * (env[1] + env[2]))
    np.testing.assert_array_equal(rows[0], env[0])
    np.testing.assert_array_equal(rows[-1], env[-1])


def test_mitsuba_envmap_emits_our_latlong_convention():
    """The emitter's radiance towards random world directions equals our bilinear lookup of the same map."""
    generator = torch.Generator().manual_seed(0)
    env = torch.rand(16, 32, 3, generator=generator) * 4.0
    emitter = mi.load_dict(envmap_emitter(env.numpy()))
    directions = torch.nn.functional.normalize(torch.randn(500, 3, generator=generator, dtype=torch.float64), dim=-1)
    axes = torch.eye(3, dtype=torch.float64)[:2]  # +x, +y (the poles' own u is arbitrary, so not +-z)
    directions = torch.cat([directions, axes, -axes])
    towards_scene = (-directions).numpy()
    interaction = mi.SurfaceInteraction3f()
    if mi.variant().startswith("scalar"):
        values = []
        for w in towards_scene:
            interaction.wi = mi.Vector3f(*w)
            values.append(np.array(emitter.eval(interaction)))
        emitted = np.stack(values)
    else:
        import drjit as dr

        interaction = dr.zeros(mi.SurfaceInteraction3f, len(towards_scene))
        interaction.wi = mi.Vector3f(towards_scene[:, 0], towards_scene[:, 1], towards_scene[:, 2])
        emitted = np.array(emitter.eval(interaction)).reshape(3, -1).T
    expected = lookup_envmap(env.double(), directions).numpy()
    np.testing.assert_allclose(emitted, expected, atol=1e-4)


def test_bilinear_lookup_is_mitsubas_bitmap_lookup():
    """The ground truth reads textures with our numpy lookup; it must be Mitsuba's, texel for texel."""
    from matspray.synth.mitsuba_scene import bitmap_texture

    rng = np.random.default_rng(0)
    texture = rng.uniform(size=(8, 16, 3)).astype(np.float32)
    uv = np.concatenate([rng.uniform(size=(300, 2)), [[0.0, 0.0], [1.0, 1.0], [0.999, 0.001]]])
    bitmap = mi.load_dict(bitmap_texture(texture))
    if mi.variant().startswith("scalar"):
        looked_up = []
        for u, v in uv:
            interaction = mi.SurfaceInteraction3f()
            interaction.uv = mi.Point2f(u, v)
            looked_up.append(np.array(bitmap.eval(interaction)))
        mitsuba_values = np.stack(looked_up)
    else:
        import drjit as dr

        interaction = dr.zeros(mi.SurfaceInteraction3f, len(uv))
        interaction.uv = mi.Point2f(uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32))
        mitsuba_values = np.array(bitmap.eval(interaction)).reshape(3, -1).T
    np.testing.assert_allclose(
        bilinear_lookup(texture, uv.astype(np.float32).astype(np.float64)), mitsuba_values, atol=2e-5
    )


def test_white_furnace_render_matches_base_color_in_linear_and_srgb(tmp_path):
    """A rough dielectric sphere under a constant white sky reflects about its base colour: the diffuse
    lobe gives the base colour, the 4% specular lobe adds a few hundredths. A colour-space mistake
    (sRGB textures, gamma-encoded output) would be off by 0.15 or more."""
    base = np.array([0.8, 0.5, 0.25])
    parts = sphere(np.random.default_rng(0))
    scene = build_scene(parts, [uniform_textures(base, 1.0, 0.0)], np.ones((8, 16, 3), np.float32))
    camera = Camera.look_at([3.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.69, 24, 24)
    rgb, alpha = render_view(scene, camera, spp=64, seed=1)
    inside = alpha > 0.999
    assert inside.sum() > 150
    mean = rgb[inside].mean(0)
    assert np.all(mean >= base - 0.01) and np.all(mean <= base + 0.07), mean
    write_render(tmp_path / "furnace.png", rgb, alpha)
    stored, stored_alpha = read_image(tmp_path / "furnace.png")
    np.testing.assert_allclose(stored[torch.from_numpy(inside)].mean(0).numpy(), mean, atol=0.01)
    np.testing.assert_allclose(stored_alpha.numpy(), alpha, atol=1.0 / 255)


def test_metal_mirror_reflects_the_constant_sky_times_base_color():
    """A metallic sphere has F0 = base colour: under a constant sky it reflects the base colour too."""
    base = np.array([0.9, 0.6, 0.3])
    scene = build_scene(
        sphere(np.random.default_rng(0)), [uniform_textures(base, 0.2, 1.0)], np.ones((8, 16, 3), np.float32)
    )
    camera = Camera.look_at([0.0, -3.5, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.69, 24, 24)
    rgb, alpha = render_view(scene, camera, spp=16, seed=2)
    centre = rgb[alpha > 0.999].mean(0)
    np.testing.assert_allclose(centre, base, atol=0.06)


@pytest.fixture(scope="module")
def textured_sphere():
    rng = np.random.default_rng(7)
    parts = sphere(rng)
    textures = [bake_textures(random_material(rng), parts[0], height=64)]
    scene = build_scene(parts, textures, np.ones((8, 16, 3), np.float32))
    camera = Camera.look_at([2.2, -2.0, 1.5], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.69, 24, 24)
    return parts[0], textures[0], scene, camera


def analytic_sphere_hits(camera: Camera, radius: float, samples: int):
    """Exact ray-sphere hits of the s x s subpixel rays: points [R, 3], hit mask [R], distance [R]."""
    origins, directions = (x.double().numpy() for x in camera.rays(samples))
    b = (origins * directions).sum(-1)
    c = (origins**2).sum(-1) - radius**2
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return origins + t[:, None] * directions, disc > 0, t


def test_ground_truth_maps_equal_texture_values_at_the_surface_points(textured_sphere):
    part, texture, scene, camera = textured_sphere
    truth = cast_ground_truth(scene, [texture], camera, samples_per_side=4)
    points, hit, _ = analytic_sphere_hits(camera, part.params["radius"], 4)
    rotation = np.asarray(part.params["rotation"])
    d = points @ rotation / part.params["radius"]  # the sphere's own frame
    uv = np.stack(
        [np.mod(np.arctan2(d[:, 1], d[:, 0]) / (2 * math.pi), 1.0), np.arccos(np.clip(d[:, 2], -1, 1)) / math.pi], -1
    )
    expected_base = bilinear_lookup(texture.base_color, uv).reshape(24, 24, 16, 3).mean(2)
    expected_rough = bilinear_lookup(texture.roughness, uv).reshape(24, 24, 16).mean(2)
    full = (truth.coverage == 1.0) & hit.reshape(24, 24, 16).all(-1)
    assert full.sum() > 100
    base_error = np.abs(truth.base_color[full] - expected_base[full])
    assert np.median(base_error) < 2e-3 and np.percentile(base_error, 98) < 0.03
    rough_error = np.abs(truth.roughness[full] - expected_rough[full])
    assert np.median(rough_error) < 2e-3 and np.percentile(rough_error, 98) < 0.03


def test_ground_truth_normals_depth_and_coverage_match_the_sphere(textured_sphere):
    part, texture, scene, camera = textured_sphere
    truth = cast_ground_truth(scene, [texture], camera, samples_per_side=4)
    points, hit, _ = analytic_sphere_hits(camera, part.params["radius"], 4)
    coverage = hit.reshape(24, 24, 16).mean(-1)
    assert np.abs(truth.coverage - coverage).mean() < 0.01
    full = (truth.coverage == 1.0) & (coverage == 1.0)
    normals = (points / part.params["radius"]).reshape(24, 24, 16, 3).mean(2)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((truth.normal[full] * normals[full]).sum(-1), -1, 1))).max() < 1.0
    depth = camera.world_to_camera(torch.from_numpy(points).float())[:, 2].numpy().reshape(24, 24, 16).mean(-1)
    np.testing.assert_allclose(truth.depth[full], depth[full], atol=2e-3)
    background = truth.coverage == 0
    assert background.sum() > 50
    assert np.all(truth.base_color[background] == 0) and np.all(truth.depth[background] == 0)
    assert np.all(truth.normal[background] == 0)


def test_sampler_keeps_the_sample_count_and_stratifies_squares():
    for spp in range(1, 70):
        sampler = mi.load_dict({"type": sampler_for(spp), "sample_count": spp})
        assert sampler.sample_count() == spp, spp
    assert sampler_for(64) == "stratified" and sampler_for(8) == "independent"


def test_stratified_renders_are_less_noisy_than_independent_ones():
    """Same sample count, a diffuse sphere under a sky with a sun: the stratified render's error
    against a 1024-spp reference is clearly below the independent sampler's."""
    import matspray.synth.mitsuba_scene as ms
    from matspray.render.shade.lights import load_envmap

    _, env = load_envmap("sky", 16)
    scene = build_scene(sphere(np.random.default_rng(0)), [uniform_textures([0.7, 0.6, 0.5], 0.8, 0.0)], env.numpy())
    camera = Camera.look_at([2.5, -2.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.69, 24, 24)
    reference, alpha = render_view(scene, camera, spp=1024, seed=3)
    inside = alpha > 0.999  # the object's interior: edge pixels divide by a noisy coverage
    errors = {}
    for sampler in ("stratified", "independent"):
        original = ms.sampler_for
        ms.sampler_for = lambda spp, s=sampler: s
        try:
            errors[sampler] = float(
                np.mean(
                    [
                        np.square(render_view(scene, camera, spp=16, seed=s)[0] - reference)[inside].mean()
                        for s in (5, 6)
                    ]
                )
            )
        finally:
            ms.sampler_for = original
    assert errors["stratified"] < 0.7 * errors["independent"], errors
