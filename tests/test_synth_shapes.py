"""Meshes, procedural materials, noise and cameras of `matspray synth` (no Mitsuba needed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from matspray.errors import ConfigError
from matspray.synth.cameras import FOV_X, make_cameras
from matspray.synth.materials import bake_textures, bilinear_lookup, evaluate_material, random_material, texel_uvs
from matspray.synth.noise import ValueNoise, fbm, voronoi
from matspray.synth.shapes import SHAPES, make_shape, resolve_shape


def welded_edges(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:  # -> [E] how many faces share each edge
    _, ids = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    f = ids.reshape(-1)[faces]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return counts


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    p = vertices[faces]
    return float(np.einsum("fi,fi->f", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("name", list(SHAPES))
def test_shapes_are_closed_outward_meshes_inside_the_unit_box(name):
    parts = make_shape(name, np.random.default_rng(0))
    assert len(parts) == (4 if name == "composite" else 1)
    for part in parts:
        assert np.abs(part.vertices).max() <= 1.0 + 1e-9
        assert part.uvs.min() >= 0.0 and part.uvs.max() <= 1.0
        assert (welded_edges(part.vertices, part.faces) == 2).all()  # watertight, no edge used thrice
        assert signed_volume(part.vertices, part.faces) > 0  # faces wind outwards
        np.testing.assert_allclose(np.linalg.norm(part.normals, axis=1), 1.0, atol=1e-9)
        p = part.vertices[part.faces]
        face_normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
        agreement = (face_normals[:, None, :] * part.normals[part.faces]).sum(-1)  # [F, 3]
        assert agreement.min() > 0.7
        # every vertex's (u, v) is where the surface function put it, so textures line up with the mesh
        np.testing.assert_allclose(part.surface(part.uvs[:, 0], part.uvs[:, 1]), part.vertices, atol=1e-12)


def test_sphere_mesh_volume_and_radius():
    part = make_shape("sphere", np.random.default_rng(1))[0]
    radius = part.params["radius"]
    np.testing.assert_allclose(np.linalg.norm(part.vertices, axis=1), radius, atol=1e-12)
    assert signed_volume(part.vertices, part.faces) == pytest.approx(4 / 3 * math.pi * radius**3, rel=2e-3)


def test_random_shape_comes_from_the_seed_and_bad_names_list_the_valid_ones():
    picks = {resolve_shape("random", seed) for seed in range(40)}
    assert picks <= set(SHAPES) and len(picks) >= 4
    assert resolve_shape("random", 7) == resolve_shape("random", 7)
    assert resolve_shape("torus", 7) == "torus"
    with pytest.raises(
        ConfigError,
        match="unknown shape 'cone' \\(valid: sphere, rounded-cube, torus, capsule, blob, composite, random\\)",
    ):
        resolve_shape("cone", 0)


@pytest.mark.parametrize("seed", range(6))
def test_materials_span_mirror_to_rough_and_dielectric_to_metal(seed):
    material = random_material(np.random.default_rng(seed))
    shown = [region.a for region in material.regions]  # A layers always show; B only where the pattern says
    roughness = [layer.roughness for layer in shown]
    metallic = {layer.metallic for layer in shown}
    assert min(roughness) == 0.05 and max(roughness) == 1.0
    assert 0.0 in metallic and 1.0 in metallic
    assert 3 <= len(material.regions) <= 5
    assert {region.pattern for region in material.regions} >= {"plain", "stripes", "noise"}


def test_material_values_cover_their_ranges_on_a_surface():
    rng = np.random.default_rng(4)
    part = make_shape("sphere", rng)[0]
    material = random_material(rng)
    u, v = texel_uvs(64, 128)
    base, rough, metal = evaluate_material(material, part.surface(u, v).reshape(-1, 3))
    assert base.min() >= 0 and base.max() <= 1 and rough.min() >= 0.05 and rough.max() <= 1.0
    assert rough.min() < 0.15 and rough.max() > 0.9  # mirror-like and rough areas both show
    assert (metal < 0.01).mean() > 0.05 and (metal > 0.99).mean() > 0.05
    assert len(np.unique(np.round(base, 2), axis=0)) > 100  # patterns and noise, not flat colours


def test_baked_textures_hold_the_material_at_texel_centres():
    rng = np.random.default_rng(5)
    part = make_shape("capsule", rng)[0]
    material = random_material(rng)
    textures = bake_textures(material, part, height=16)
    u, v = texel_uvs(16, 32)
    base, rough, metal = evaluate_material(material, part.surface(u, v).reshape(-1, 3))
    np.testing.assert_allclose(textures.base_color.reshape(-1, 3), base, atol=1e-6)
    np.testing.assert_allclose(textures.roughness.reshape(-1), rough, atol=1e-6)
    np.testing.assert_allclose(textures.metallic.reshape(-1), metal, atol=1e-6)


def test_bilinear_lookup_hits_texels_at_centres_and_wraps():
    texture = np.arange(4 * 6, dtype=np.float64).reshape(4, 6)
    u, v = texel_uvs(4, 6)
    centres = np.stack([u.reshape(-1), v.reshape(-1)], -1)
    np.testing.assert_allclose(bilinear_lookup(texture, centres), texture.reshape(-1))
    np.testing.assert_allclose(
        bilinear_lookup(texture, np.array([[0.0, 1.5 / 4]])), [0.5 * (texture[1, 0] + texture[1, 5])]
    )
    np.testing.assert_allclose(
        bilinear_lookup(texture, np.array([[1.5 / 6, 0.0]])), [0.5 * (texture[0, 1] + texture[3, 1])]
    )


def test_noise_is_seeded_bounded_and_smooth():
    points = np.random.default_rng(0).uniform(-2, 2, size=(2000, 3))
    a, b = ValueNoise(np.random.default_rng(3)), ValueNoise(np.random.default_rng(3))
    np.testing.assert_array_equal(a(points), b(points))
    values = fbm(a, points, 3.0)
    assert np.abs(values).max() <= 1.0 and values.std() > 0.05
    step = fbm(a, points + 1e-4, 3.0) - values
    assert np.abs(step).max() < 0.05  # continuous: a tiny move changes little


def test_voronoi_matches_brute_force():
    rng = np.random.default_rng(1)
    points, sites = rng.normal(size=(500, 3)), rng.normal(size=(6, 3))
    nearest, gap = voronoi(points, sites, chunk=64)
    distance = np.linalg.norm(points[:, None] - sites[None], axis=-1)
    ordered = np.sort(distance, axis=1)
    np.testing.assert_array_equal(nearest, distance.argmin(1))
    np.testing.assert_allclose(gap, ordered[:, 1] - ordered[:, 0], atol=1e-12)


def test_cameras_frame_the_object_and_train_and_test_differ():
    train, test, distance = make_cameras(20, 5, 1.0, 64, np.random.default_rng(0))
    assert len(train) == 20 and len(test) == 5
    centres = torch.stack([c.center for c in train + test]).double()
    torch.testing.assert_close(
        centres.norm(dim=-1), torch.full((25,), distance, dtype=torch.float64), atol=1e-4, rtol=0
    )
    gaps = torch.cdist(centres[20:], centres[:20])
    assert gaps.min() > 1e-3  # no test camera repeats a training camera
    assert centres[:, 2].min() < 0 < centres[:, 2].max()  # views from below and above
    for camera in train + test:
        assert abs(camera.fov_x - FOV_X) < 1e-6
        pixels, _ = camera.project(torch.zeros(1, 3))
        torch.testing.assert_close(pixels[0], torch.tensor([32.0, 32.0]), atol=1e-3, rtol=0)
        # the unit bounding sphere fills most of the frame but stays inside it
        half_angle = math.asin(1.0 / distance)
        assert 0.85 * FOV_X / 2 < half_angle < FOV_X / 2


def test_turntable_cameras_circle_one_ring_looking_at_the_object():
    from matspray.synth.cameras import TURNTABLE_ELEVATION

    train, test, distance = make_cameras(12, 4, 1.0, 64, np.random.default_rng(0), layout="turntable")
    centres = torch.stack([c.center for c in train + test]).double()
    elevation = torch.rad2deg(torch.asin(centres[:, 2] / centres.norm(dim=-1)))
    torch.testing.assert_close(
        elevation, torch.full((16,), TURNTABLE_ELEVATION, dtype=torch.float64), atol=1e-4, rtol=0
    )
    torch.testing.assert_close(
        centres.norm(dim=-1), torch.full((16,), distance, dtype=torch.float64), atol=1e-4, rtol=0
    )
    azimuths = torch.atan2(centres[:12, 1], centres[:12, 0])
    steps = torch.remainder(azimuths.roll(-1) - azimuths, 2 * math.pi)
    torch.testing.assert_close(steps, torch.full((12,), 2 * math.pi / 12, dtype=torch.float64), atol=1e-5, rtol=0)
    assert torch.cdist(centres[12:], centres[:12]).min() > 1e-3  # test cameras between the training ones
    for camera in train + test:
        pixels, _ = camera.project(torch.zeros(1, 3))
        torch.testing.assert_close(pixels[0], torch.tensor([32.0, 32.0]), atol=1e-3, rtol=0)


def test_camera_layout_is_checked_and_kept_out_of_older_objects_identity():
    from matspray.errors import SettingError
    from matspray.synth import SynthConfig

    assert "cameras" not in SynthConfig().identity()  # objects made before the setting keep their identity
    assert SynthConfig(cameras="turntable").identity()["cameras"] == "turntable"
    with pytest.raises(SettingError, match="cameras.*must be one of sphere, turntable, front, got 'ring'"):
        SynthConfig(cameras="ring").validate()


def test_front_cameras_see_the_object_from_one_side_up_to_45_degrees_and_fill_sets_the_distance():
    from matspray.synth.cameras import FRONT_HALF_AZIMUTH, framing_distance

    train, test, distance = make_cameras(24, 6, 1.0, 32, np.random.default_rng(0), 10.0, "front", fill=1.1)
    assert distance == pytest.approx(1.0 / math.sin(0.5 * FOV_X * 1.1)) == framing_distance(1.0, fill=1.1)
    azimuths = []
    for camera in train + test:
        c = camera.center.double()
        elevation = math.degrees(math.asin(float(c[2] / c.norm())))
        assert 10.0 - 1e-6 <= elevation <= 45.0 + 1e-6
        azimuths.append(math.degrees(math.atan2(float(c[0]), float(-c[1]))))  # 0: straight in front (-y)
        pixels, _ = camera.project(torch.zeros(1, 3))
        torch.testing.assert_close(pixels[0], torch.tensor([16.0, 16.0]), atol=1e-3, rtol=0)  # looks at the object
    assert max(abs(a) for a in azimuths) <= FRONT_HALF_AZIMUTH + 1e-6  # never from behind
    assert max(azimuths[:24]) - min(azimuths[:24]) > 120.0  # the training views spread over the front half


def test_one_sided_settings_are_checked_and_kept_out_of_older_objects_identity():
    from matspray.errors import SettingError
    from matspray.synth import SynthConfig

    assert not {"fill", "tabletop"} & set(SynthConfig().identity())  # objects made before keep their identity
    made = SynthConfig(fill=1.1, tabletop="white-on-dark", ground=True, cameras="front")
    made.validate()
    assert {k: made.identity()[k] for k in ("fill", "tabletop", "cameras")} == {
        "fill": 1.1,
        "tabletop": "white-on-dark",
        "cameras": "front",
    }
    for settings, message in (
        ({"fill": 0.1}, r"fill.*must be a number in \[0.2, 2\], got 0.1"),
        ({"fill": True}, "fill.*got True"),
        ({"tabletop": "red", "ground": True}, "tabletop.*must be one of grey, white-on-dark, dark-on-light"),
        ({"tabletop": "dark-on-light"}, "tabletop.*is a table: it needs the ground"),
    ):
        with pytest.raises(SettingError, match=message):
            SynthConfig(**settings).validate()


def test_tabletop_tones_and_table_texture():
    from matspray.synth.materials import TABLES, Textures, table_texture, toned

    g = np.random.default_rng(0)
    textures = Textures(g.uniform(0, 1, (8, 16, 3)), g.uniform(0, 1, (8, 16)), g.uniform(0, 1, (8, 16)))
    white, dark = toned(textures, "white-on-dark"), toned(textures, "dark-on-light")
    assert white.base_color.min() >= 0.62 * 0.88 - 1e-9 and white.base_color.max() <= 0.92 + 1e-9
    assert dark.base_color.max() <= 0.1 + 1e-9
    for tone in (white, dark):
        assert not tone.metallic.any() and np.array_equal(tone.roughness, textures.roughness)  # dielectric
        luminance = textures.base_color.mean(-1)
        assert np.corrcoef(tone.base_color[..., 0].ravel(), luminance.ravel())[0, 1] > 0.99  # keeps its pattern
    for tabletop in ("white-on-dark", "dark-on-light"):
        table = table_texture(tabletop, seed=3, texels=64)
        assert table.shape == (64, 64, 3) and 0.0 <= table.min() and table.max() <= 1.0
        np.testing.assert_allclose(table.reshape(-1, 3).mean(0), TABLES[tabletop], rtol=0.2)
        assert table[..., 0].std() > 0.1 * TABLES[tabletop][0]  # grain and blotches: a textured table
        assert np.array_equal(table, table_texture(tabletop, seed=3, texels=64))
