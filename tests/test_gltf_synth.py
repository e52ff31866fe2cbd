"""`matspray synth --asset`: glTF assets rendered and ray cast; ground truth against brute-force texel
references (KHR_texture_transform, every wrap mode, factors, several materials), and the round trip
procedural object -> object.glb -> `synth --asset` at test sizes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("pygltflib")

from matspray.cli import main  # noqa: E402
from matspray.data.camera import Camera  # noqa: E402
from matspray.data.images import read_raw  # noqa: E402
from matspray.errors import DataError  # noqa: E402
from matspray.gltf import PbrMaterial, Primitive, TextureRef, TextureTransform, read_gltf, write_glb  # noqa: E402
from matspray.synth import SynthConfig, make_object  # noqa: E402
from matspray.synth.gltf_object import GLTF_TO_WORLD, asset_parts  # noqa: E402
from matspray.synth.groundtruth import cast_ground_truth  # noqa: E402
from matspray.synth.materials import Sampling, srgb_to_linear, texture_lookup  # noqa: E402
from matspray.synth.mitsuba_scene import bitmap_texture, build_scene, select_variant  # noqa: E402

SMALL = dict(resolution=24, train_views=2, test_views=1, spp=16, texture_height=32, env_height=16, gt_samples=2)
QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)  # glTF frame, facing +Z
FACES = np.array([[0, 1, 2], [0, 2, 3]])
UV_LOW, UV_SPAN = np.array([-0.7, -0.6]), np.array([2.4, 2.2])  # uv = UV_LOW + UV_SPAN * (x, y): beyond [0, 1]


@pytest.fixture(scope="module", autouse=True)
def variant():
    return select_variant()


def q8(image):
    return np.round(np.asarray(image) * 255) / 255


def reference_lookup(image, uv, matrix, wrap_s, wrap_t):  # brute force: texel indices wrapped by period parity
    uv = uv @ matrix[:2, :2].T + matrix[:2, 2]
    height, width = image.shape[:2]

    def wrap(i, n, mode):
        if mode == "clamp":
            return np.clip(i, 0, n - 1)
        period, rest = np.floor_divide(i, n), np.mod(i, n)
        return rest if mode == "repeat" else np.where(period % 2 == 0, rest, n - 1 - rest)

    x, y = uv[:, 0] * width - 0.5, uv[:, 1] * height - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    out = 0.0
    for dy in (0, 1):
        for dx in (0, 1):
            weight = (1 - abs(x - x0 - dx)) * (1 - abs(y - y0 - dy))
            out = (
                out
                + weight[:, None]
                * image[wrap(y0 + dy, height, wrap_t)][np.arange(len(x)), wrap(x0 + dx, width, wrap_s)]
            )
    return out


def quad_camera(resolution=24):
    # the quad lies in world y = 0 (glTF z = 0), x and z in [0, 1]; look at it from -y
    return Camera.look_at([0.5, -2.2, 0.5], [0.5, 0.0, 0.5], [0.0, 0.0, 1.0], 0.5, resolution, resolution)


def surface_uv(camera, samples):  # -> uv [R, 2] of each subpixel ray on the quad's plane, hit [R]
    origins, directions = (t.double().numpy() for t in camera.rays(samples))
    t = -origins[:, 1] / directions[:, 1]
    point = origins + t[:, None] * directions
    xy = np.stack([point[:, 0], point[:, 2]], -1)  # glTF x, y
    hit = (xy >= 0).all(-1) & (xy <= 1).all(-1)
    return UV_LOW + UV_SPAN * xy, hit


@pytest.mark.parametrize(
    "wrap", [("repeat", "repeat"), ("clamp", "clamp"), ("mirror", "mirror"), ("repeat", "mirror"), ("clamp", "repeat")]
)
def test_ground_truth_is_the_texel_at_the_surface_point(tmp_path, wrap):
    rng = np.random.default_rng(7)
    colour, packed = q8(rng.uniform(size=(3, 4, 3))), q8(rng.uniform(size=(5, 3, 3)))
    base_transform = TextureTransform((0.1, -0.2), 0.35, (1.3, 0.8))
    mr_transform = TextureTransform((0.05, 0.15), -0.6, (0.9, 1.7))
    material = PbrMaterial(
        "quad",
        (0.9, 0.8, 0.6, 1.0),
        0.8,
        0.6,
        TextureRef(colour, 1, base_transform, *wrap),
        TextureRef(packed, 1, mr_transform, wrap[1], wrap[0]),
    )
    uvs = UV_LOW + UV_SPAN * QUAD[:, :2]
    path = tmp_path / "quad.glb"
    write_glb(path, [Primitive("quad", QUAD, FACES, (np.zeros((4, 2)), uvs), None, 0)], [material])
    parts, textures, matrix = asset_parts(read_gltf(path), "keep")
    np.testing.assert_allclose(matrix[:3, :3], GLTF_TO_WORLD)
    scene = build_scene(parts, textures, np.ones((8, 16, 3), np.float32))
    camera = quad_camera()
    truth = cast_ground_truth(scene, textures, camera, samples_per_side=2)
    uv, hit = surface_uv(camera, 2)
    expected_base = reference_lookup(srgb_to_linear(colour), uv, base_transform.matrix(), *wrap) * [
        0.9,
        0.8,
        0.6,
    ]  # decoded, then filtered
    expected_mr = reference_lookup(packed, uv, mr_transform.matrix(), wrap[1], wrap[0])
    full = hit.reshape(24, 24, 4).all(-1)
    assert full.sum() > 200 and np.array_equal(truth.coverage == 1.0, full)
    mean = lambda values: values.reshape(24, 24, 4, -1).mean(2)[full]  # noqa: E731
    np.testing.assert_allclose(truth.base_color[full], mean(expected_base), atol=2e-4)
    np.testing.assert_allclose(truth.roughness[full], mean(expected_mr[:, 1] * 0.6)[:, 0], atol=2e-4)
    np.testing.assert_allclose(truth.metallic[full], mean(expected_mr[:, 2] * 0.8)[:, 0], atol=2e-4)


@pytest.mark.parametrize(
    "wrap", [("repeat", "repeat"), ("clamp", "clamp"), ("mirror", "mirror"), ("mirror", "clamp"), ("clamp", "repeat")]
)
def test_mitsuba_reads_a_texture_as_the_ground_truth_does(wrap):
    """The renderer's bitmap (its to_uv, its one wrap mode; mixed modes unwrapped over the mesh's UVs) is our lookup."""
    import drjit as dr
    import mitsuba as mi

    rng = np.random.default_rng(3)
    texture = rng.uniform(size=(5, 7, 3)).astype(np.float32)
    sampling = Sampling(TextureTransform((0.2, -0.1), 0.5, (1.5, 0.6)).matrix(), *wrap)
    mesh_uvs = rng.uniform(-1.5, 2.5, size=(50, 2))
    weights = rng.dirichlet(np.ones(3), size=400)  # points inside triangles of mesh UVs, as a mesh's surface has
    uv = np.einsum("nk,nkc->nc", weights, mesh_uvs[rng.integers(0, 50, size=(400, 3))]).astype(np.float32)
    bitmap = mi.load_dict(bitmap_texture(texture, sampling, mesh_uvs))
    interaction = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    interaction.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    mitsuba_values = np.array(bitmap.eval(interaction)).reshape(3, -1).T
    np.testing.assert_allclose(texture_lookup(texture, uv.astype(np.float64), sampling), mitsuba_values, atol=3e-5)


def test_two_primitives_two_materials_factors_and_the_default_material(tmp_path):
    path = tmp_path / "two.glb"
    left, right = QUAD * [0.45, 1, 1], QUAD * [0.45, 1, 1] + [0.55, 0, 0]
    write_glb(
        path,
        [Primitive("left", left, FACES, (), None, 0), Primitive("right", right, FACES, (), None, None)],
        [PbrMaterial("red", (0.8, 0.1, 0.2, 1.0), 0.25, 0.4)],
    )
    parts, textures, _ = asset_parts(read_gltf(path), "keep")
    assert [p.params["material"] for p in parts] == ["red", "default"]
    truth = cast_ground_truth(build_scene(parts, textures, np.ones((8, 16, 3), np.float32)), textures, quad_camera(), 2)
    x = (
        np.linspace(0.5 - 0.5 * 2.2 * math.tan(0.25), 0.5 + 0.5 * 2.2 * math.tan(0.25), 24, endpoint=False)
        + 1.1 * math.tan(0.25) / 24
    )
    full = truth.coverage == 1.0
    on_left, on_right = full & (x < 0.43)[None, :], full & (x > 0.57)[None, :]
    assert on_left.sum() > 50 and on_right.sum() > 50
    np.testing.assert_allclose(truth.base_color[on_left], np.tile([0.8, 0.1, 0.2], (on_left.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(truth.roughness[on_left], 0.4, atol=1e-6)
    np.testing.assert_allclose(truth.metallic[on_left], 0.25, atol=1e-6)
    np.testing.assert_allclose(
        truth.base_color[on_right], 1.0, atol=1e-6
    )  # glTF's default: white, metallic 1, roughness 1
    np.testing.assert_allclose(truth.roughness[on_right], 1.0, atol=1e-6)
    np.testing.assert_allclose(truth.metallic[on_right], 1.0, atol=1e-6)


def test_fit_placement_centres_scales_and_is_recorded_as_asset_to_world(tmp_path):
    path = tmp_path / "off.glb"
    box = QUAD * [4.0, 2.0, 1.0] + [10.0, -3.0, 5.0]
    write_glb(path, [Primitive("far", box, FACES, (), None, None)], [])
    asset = read_gltf(path)
    parts, _, matrix = asset_parts(asset, "fit")
    world = parts[0].vertices
    np.testing.assert_allclose(0.5 * (world.min(0) + world.max(0)), 0.0, atol=1e-12)
    assert np.linalg.norm(world, axis=1).max() == pytest.approx(1.0)
    corners = asset.primitives[0].positions[asset.primitives[0].indices.reshape(-1)]  # no normals: split per face
    np.testing.assert_allclose(corners @ matrix[:3, :3].T + matrix[:3, 3], world, atol=1e-12)
    out = tmp_path / "synth"
    make_object(SynthConfig(asset=str(path), seed=1, **SMALL), out, progress=False, notify=lambda _: None)
    record = json.loads((out / "scene.json").read_text())
    assert record["shape"] == "asset" and record["status"] == "complete"
    np.testing.assert_allclose(record["asset"]["asset_to_world"], matrix)
    # glTF +Y (the box's 2-unit side) is world up: the object is taller (z) than deep (y)
    assert np.ptp(world[:, 2]) > np.ptp(world[:, 1])


def psnr(a, b):
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def test_round_trip_through_object_glb_reproduces_images_and_ground_truth(tmp_path):
    settings = dict(seed=4, **SMALL)
    make_object(SynthConfig(shape="composite", **settings), tmp_path / "made", progress=False, notify=lambda _: None)
    notes = []
    make_object(
        SynthConfig(asset=str(tmp_path / "made" / "object.glb"), placement="keep", **settings),
        tmp_path / "again",
        progress=False,
        notify=notes.append,
    )
    assert not [n for n in notes if "ignored" in n]
    compared = 0
    for made in sorted((tmp_path / "made").glob("*/r_*.png")):
        again = tmp_path / "again" / made.relative_to(tmp_path / "made")
        assert psnr(read_raw(made).numpy(), read_raw(again).numpy()) > 35.0, made.name
        compared += 1
    assert compared == 3 * 4 + 2  # renders and their 3 maps for 3 views, 2 relit test views
    first = json.loads((tmp_path / "made" / "scene.json").read_text())["cameras"]
    second = json.loads((tmp_path / "again" / "scene.json").read_text())["cameras"]
    assert first["distance"] == pytest.approx(second["distance"], rel=1e-6)


def test_cli_rejects_bad_assets_in_one_line_and_writes_nothing(tmp_path, capsys):
    path = tmp_path / "good.glb"
    write_glb(path, [Primitive("quad", QUAD, FACES)], [])
    data = path.read_bytes()
    cut = tmp_path / "cut.glb"
    cut.write_bytes(data[:-16])
    out = tmp_path / "out"
    code = main(["synth", "--out", str(out), "--asset", str(cut), "--res", "16", "--views", "1", "--test-views", "0"])
    err = capsys.readouterr().err
    assert code == 2 and "cut.glb" in err and "truncated" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())
    code = main(["synth", "--out", str(out), "--asset", str(path), "--shape", "sphere"])
    assert code == 2 and "--shape and --asset" in capsys.readouterr().err
    with pytest.raises(DataError, match="two UV sets"):
        two = tmp_path / "two.glb"
        image = np.zeros((2, 2, 3))
        write_glb(
            two,
            [Primitive("q", QUAD, FACES, (QUAD[:, :2], QUAD[:, :2]), None, 0)],
            [PbrMaterial(base_color_texture=TextureRef(image, 0), metallic_roughness_texture=TextureRef(image, 1))],
        )
        make_object(SynthConfig(asset=str(two), **SMALL), tmp_path / "out2", progress=False, notify=lambda _: None)
    assert not (tmp_path / "out2").exists()


@pytest.mark.parametrize("double_sided", [False, True])
def test_a_double_sided_face_is_shaded_from_behind_with_its_normal_turned(tmp_path, double_sided):
    from matspray.synth.mitsuba_scene import render_view

    path = tmp_path / "plane.glb"
    back_first = FACES[:, [0, 2, 1]]  # the quad's front faces away from the camera (glTF -Z, world +y)
    write_glb(
        path,
        [Primitive("plane", QUAD, back_first, (), None, 0)],
        [PbrMaterial("grey", (0.5, 0.5, 0.5, 1.0), 0.0, 1.0, double_sided=double_sided)],
    )
    parts, textures, _ = asset_parts(read_gltf(path), "keep")
    scene = build_scene(parts, textures, np.ones((8, 16, 3), np.float32))
    camera = quad_camera(16)
    truth = cast_ground_truth(scene, textures, camera, 1)
    rgb, alpha = render_view(scene, camera, 16, 0)
    full = truth.coverage == 1.0
    assert full.sum() > 50 and (alpha[full] > 0.99).all()
    if double_sided:  # a rough grey dielectric under a white sky: about its albedo, and facing the camera (-y)
        assert 0.3 < float(rgb[full].mean()) < 0.7
        np.testing.assert_allclose(truth.normal[full], np.tile([0.0, -1.0, 0.0], (full.sum(), 1)), atol=1e-5)
    else:
        assert float(rgb[full].max()) < 1e-3
        np.testing.assert_allclose(truth.normal[full], np.tile([0.0, 1.0, 0.0], (full.sum(), 1)), atol=1e-5)


def test_a_texture_tiled_too_far_for_two_wrap_modes_is_refused_before_writing(tmp_path):
    path = tmp_path / "tiled.glb"
    image = np.zeros((64, 64, 3))
    write_glb(
        path,
        [Primitive("q", QUAD, FACES, (QUAD[:, :2] * 200.0,), None, 0)],
        [PbrMaterial(base_color_texture=TextureRef(image, 0, TextureTransform(), "repeat", "clamp"))],
    )
    with pytest.raises(DataError, match="tiled.glb: mesh 'q': a texture with wraps repeat/clamp"):
        make_object(SynthConfig(asset=str(path), **SMALL), tmp_path / "out", progress=False, notify=lambda _: None)
    assert not (tmp_path / "out").exists()
