"""The camera light (`method.refine.camera_light`): a flash at each photo's camera, its BRDF term against the
microfacet model written out by hand, which photos it lights (EXIF), its file, refinement learning it, and held-out
scoring using it."""

import math

import pytest
import torch
from PIL import Image

from matspray.data.images import flash_fired
from matspray.errors import DataError, SettingError
from matspray.method.asset import Asset, read_asset, write_asset
from matspray.method.refine.camera_light import CAMERA_LIGHT_FILE, CameraLight, falloff, lit_views
from matspray.method.refine.loop import RefineConfig, RefineInputs, refine
from matspray.method.relight import flash_radiance, render_gbuffer, render_relit
from matspray.render.shade.brdf import camera_light_radiance
from matspray.render.shade.envmap import EnvironmentMap
from tests.scenes import lift_material_scene, material_scene, ring_cameras, sky_map, sphere_of_disks

BOUNDS = torch.tensor([[-1.2] * 3, [1.2] * 3])


def by_hand(base, roughness, metallic, cos, irradiance):  # [P, 3], [P], [P], [P] n.v of a facing normal, [P, 3]
    """E f_r(v, v) (n.v) for a light at the eye (h = v): Lambert plus F0 D(n.v) G2 / (4 (n.v)^2), Schlick at v.h = 1."""
    a2 = roughness.clamp(0.04, 1.0) ** 4
    d = a2 / (math.pi * (cos**2 * (a2 - 1) + 1) ** 2)
    g2 = 1.0 / (1.0 + 2.0 * (torch.sqrt(1.0 + a2 * (1.0 - cos**2) / cos**2) - 1.0) / 2.0)  # Smith, l = v
    f0 = 0.04 * (1 - metallic[:, None]) + base * metallic[:, None]
    specular = f0 * (d * g2 / (4 * cos * cos))[:, None]
    diffuse = base * (1 - metallic[:, None]) / math.pi
    return (diffuse + specular) * irradiance * cos[:, None]


def test_the_flash_term_is_the_microfacet_brdf_at_the_eye():
    g = torch.Generator().manual_seed(0)
    count = 64
    base, roughness, metallic = torch.rand(count, 3, generator=g), torch.rand(count, generator=g), torch.rand(count)
    wo = torch.nn.functional.normalize(torch.randn(count, 3, generator=g, dtype=torch.float64), dim=-1)
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g, dtype=torch.float64), dim=-1)
    cos = (normals * wo).sum(-1)
    irradiance = torch.rand(count, 3, generator=g, dtype=torch.float64) + 0.5
    base, roughness, metallic = base.double(), roughness.double(), metallic.double()
    got = camera_light_radiance(base, roughness, metallic, normals * 2.5, wo, irradiance)
    # a normal facing away is turned to face the camera, as split-sum shading turns it
    expected = by_hand(base, roughness, metallic, cos.abs(), irradiance)
    torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-12)
    flipped = camera_light_radiance(base, roughness, metallic, -normals, wo, irradiance)
    torch.testing.assert_close(flipped, got, rtol=1e-12, atol=1e-15)


def test_the_flash_term_has_the_gradients_of_finite_differences():
    g = torch.Generator().manual_seed(1)
    inputs = [
        torch.rand(5, 3, generator=g, dtype=torch.float64),
        0.2 + 0.7 * torch.rand(5, generator=g, dtype=torch.float64),
        torch.rand(5, generator=g, dtype=torch.float64),
        torch.tensor([[0.1, 0.2, 1.0]] * 5, dtype=torch.float64) + 0.1 * torch.rand(5, 3, generator=g),
    ]
    wo = torch.nn.functional.normalize(torch.tensor([[0.0, 0.3, 1.0]] * 5, dtype=torch.float64), dim=-1)
    irradiance = torch.rand(5, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    inputs = [x.requires_grad_(True) for x in inputs]
    assert torch.autograd.gradcheck(
        lambda b, r, m, n, e: camera_light_radiance(b, r, m, n, wo, e), (*inputs, irradiance), eps=1e-6, atol=1e-7
    )


def test_the_falloff_is_the_inverse_square_of_the_blended_distance():
    alpha = torch.tensor([[1.0, 0.5, 0.0, 1.0]])
    distance = torch.tensor([[2.0, 0.5, 0.0, 0.0]])  # blended: sum w d (the second pixel: d = 1 at half coverage)
    got = falloff(distance, alpha, reference=2.0)[..., 0]
    # 2 / 2, 2 / 1; an uncovered pixel at d0; a covered one at distance 0 held at 1 % of d0
    torch.testing.assert_close(got, torch.tensor([[1.0, 4.0, 1.0, 1e4]]))


def photo(path, flash: int | None):
    exif = Image.Exif()
    if flash is not None:
        exif.get_ifd(0x8769)[0x9209] = flash
    Image.new("RGB", (4, 4), (200, 100, 50)).save(path, exif=exif.tobytes())
    return path


def test_the_photos_exif_says_which_a_flash_lit(tmp_path):
    fired, not_fired, none = (
        photo(tmp_path / "a.jpg", 9),
        photo(tmp_path / "b.jpg", 16),
        photo(tmp_path / "c.jpg", None),
    )
    png = tmp_path / "d.png"
    Image.new("RGB", (4, 4)).save(png)
    broken = tmp_path / "e.jpg"
    broken.write_bytes(b"not a jpeg")
    paths = [fired, not_fired, none, png, broken, None]
    assert [flash_fired(p) for p in paths] == [True, False, False, False, False, False]
    assert lit_views("auto", paths) == [True, False, False, False, False, False]
    assert lit_views("on", paths) == [True] * 6 and lit_views("off", paths) == [False] * 6
    with pytest.raises(SettingError, match="camera_light.*unknown mode 'flash'.*auto, on, off"):
        lit_views("flash", paths)
    with pytest.raises(SettingError, match="camera_light.*unknown mode 'always'"):
        RefineConfig(camera_light="always")


def test_the_camera_light_file_round_trips_and_a_broken_one_is_one_line(tmp_path):
    light = CameraLight(torch.tensor([0.5, 1.5, 2.0]), 3.25, "on")
    path = tmp_path / CAMERA_LIGHT_FILE
    light.save(path)
    loaded = CameraLight.load(path)
    torch.testing.assert_close(loaded.intensity, light.intensity.detach())
    assert loaded.reference_distance == 3.25 and loaded.views == "on" and not loaded.log_intensity.requires_grad
    for text in ('{"format": "matspray-camera-light-1", "intensity": [1, 1], "reference_distance": 1}', "{", "[]"):
        path.write_text(text)
        with pytest.raises(DataError) as error:
            CameraLight.load(path)
        assert str(error.value).startswith(str(path)) and "\n" not in str(error.value)
    path.write_text('{"format": "matspray-camera-light-1", "intensity": [1, -1, 1], "reference_distance": 1}')
    with pytest.raises(DataError, match="negative"):
        CameraLight.load(path)


def test_refinement_learns_a_flash_that_lit_the_photos(tmp_path):
    gaussians, normals, materials, views, maps = material_scene(n_views=8)
    asset = Asset(gaussians, materials, normals)
    sky = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    truth = CameraLight(torch.full((3,), 2.0), 3.0, "on").requires_grad_(False)
    flashed = []
    for view in views:
        rgb, alpha = render_relit(asset, view.camera, sky, camera_light=truth)
        image = rgb / alpha[..., None].clamp_min(1e-4) * (alpha[..., None] > 1e-4)
        flashed.append(type(view)(view.name, image, view.alpha, view.camera))
    lifted = lift_material_scene(gaussians, flashed, maps)
    inputs = RefineInputs(
        gaussians.subset(lifted.kept), normals[lifted.kept], lifted.values, lifted.seen, flashed, maps, BOUNDS
    )
    results = {}
    for mode in ("on", "off"):
        config = RefineConfig(iterations=60, envmap_height=4, light_warmup=40, log_every=10, camera_light=mode)
        results[mode] = refine(inputs, config, progress=False)
    on, off = results["on"], results["off"]
    assert off.camera_light is None
    assert isinstance(on.camera_light, CameraLight) and not on.camera_light.log_intensity.requires_grad
    start = RefineConfig().envmap_init
    assert float(on.camera_light.intensity.mean()) > 1.5 * start  # it was learned, towards the flash's 2
    assert on.history[-1]["photo"] < 0.8 * off.history[-1]["photo"], (on.history[-1], off.history[-1])
    # the PNG-less views (no file) under "auto" have no flash
    auto = refine(inputs, RefineConfig(iterations=2, envmap_height=4, light_warmup=1), progress=False)
    assert auto.camera_light is None

    folder = tmp_path / "asset"
    write_asset(folder, inputs.gaussians, on)
    read = read_asset(folder)
    torch.testing.assert_close(read.camera_light.intensity, on.camera_light.intensity)
    write_asset(folder, inputs.gaussians, off)  # a later asset without a flash leaves no stale file
    assert not (folder / CAMERA_LIGHT_FILE).exists() and read_asset(folder).camera_light is None


def test_a_relit_render_adds_the_flash_only_when_asked():
    gaussians, normals, materials = sphere_of_disks(seed=0)
    asset = Asset(gaussians, materials, normals)
    camera = ring_cameras(1, 24)[0]
    sky = EnvironmentMap.from_tensor(sky_map(), learnable=False).prefilter()
    flash = CameraLight(torch.tensor([1.0, 2.0, 3.0]), 3.0).requires_grad_(False)
    plain, alpha = render_relit(asset, camera, sky)
    lit, lit_alpha = render_relit(asset, camera, sky, camera_light=flash)
    added = flash_radiance(asset, camera, render_gbuffer(asset, camera), flash) * alpha[..., None]
    torch.testing.assert_close(lit, plain + added)
    torch.testing.assert_close(lit_alpha, alpha)
    assert bool((added[alpha > 0.9] > 0).all())
    twice = CameraLight(2 * flash.intensity, 3.0).requires_grad_(False)
    torch.testing.assert_close(render_relit(asset, camera, sky, camera_light=twice)[0], plain + 2 * added)
    farther = CameraLight(flash.intensity, 6.0).requires_grad_(False)  # the same light, d0 twice: 4 times as bright
    torch.testing.assert_close(render_relit(asset, camera, sky, camera_light=farther)[0], plain + 4 * added)


def test_refinement_with_a_flash_runs_as_graphs_with_the_same_results(capsys):
    # through the graph stand-in (static buffers replayed), as on a CUDA device: the flash's irradiance is an input of
    # the captured terms that needs a gradient (its intensity is learned), as the light's images are
    from benchmarks.graph_replay import graph_stand_in
    from matspray.device import capturing_with

    gaussians, normals, _, views, maps = material_scene()
    lifted = lift_material_scene(gaussians, views, maps)
    inputs = RefineInputs(
        gaussians.subset(lifted.kept), normals[lifted.kept], lifted.values, lifted.seen, views, maps, BOUNDS
    )
    config = RefineConfig(iterations=6, envmap_height=4, light_warmup=2, log_every=1, camera_light="on")
    results = []
    for graphs in (True, False):
        with capturing_with(graph_stand_in):
            results.append(refine(inputs, config, progress=False, graphs=graphs))
    graphed, eager = results
    assert "without CUDA graphs" not in capsys.readouterr().err
    assert [r["photo"] for r in graphed.history] == [r["photo"] for r in eager.history]
    torch.testing.assert_close(graphed.camera_light.intensity, eager.camera_light.intensity, rtol=0, atol=0)
    start = torch.full((3,), RefineConfig().envmap_init)
    assert not torch.allclose(eager.camera_light.intensity, start)  # learned, in both


def test_info_says_which_photos_a_flash_lit(tmp_path):
    from matspray.data.loader import describe_scene
    from matspray.data.scene import Scene

    camera = ring_cameras(1, 4)[0]
    paths = [photo(tmp_path / "a.jpg", 9), photo(tmp_path / "b.jpg", 16), photo(tmp_path / "c.jpg", 9)]
    views = [photo_view(p.stem, camera, p) for p in paths]
    lines = describe_scene(Scene(views[:2], views[2:], BOUNDS)).lines
    assert "  taken with a flash (EXIF): 1 of 2; refinement learns a flash at the camera" in "\n".join(lines)
    assert sum("taken with a flash" in line for line in lines) == 2  # the held-out split's line too
    plain = describe_scene(Scene([photo_view("d", camera, None)], [], BOUNDS)).lines
    assert not any("flash" in line for line in plain)


def photo_view(name, camera, path):
    from matspray.data.scene import View

    return View(name, torch.rand(4, 4, 3), None, camera, path)
