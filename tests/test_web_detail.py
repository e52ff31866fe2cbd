"""`matspray.web.detail`: the Gaussians the web page draws. Footprints against the page's rectangle worked out by
hand, the ranking's weights against the torch rasterizer's hit list, the ranking leaving out what no view sees
first, the choice keeping its PSNR, and `matspray export --web DIR DB` using it (and refusing what is not a PSNR)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from matspray.cli import main
from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb
from matspray.gaussians import Gaussians
from matspray.method.asset import Asset
from matspray.method.relight import orbit_spec, render_relit, spec_cameras
from matspray.render.backend import rendering_with
from matspray.render.raster.rasterize import view_weights
from matspray.render.shade.envmap import EnvironmentMap
from matspray.web.detail import colour_per_pixel, drop_order, footprint_areas, kept, page_gaussians, subset
from matspray.web.page import page_view
from tests.scenes import sky_map, sphere_cameras, sphere_of_disks, write_disk_sphere_run


def facing_gaussians(sigmas, opacities, depth=4.0) -> Gaussians:
    """Round Gaussians of world sigma `sigmas` [N] at the origin, facing a camera `depth` away on -z."""
    n = len(sigmas)
    scales = torch.tensor(sigmas, dtype=torch.float32)[:, None].expand(n, 3).clone()
    logits = torch.logit(torch.tensor(opacities, dtype=torch.float32))
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4).clone()
    return Gaussians(torch.zeros(n, 3), scales.log(), quats, logits, torch.zeros(n, 1, 3))


def test_a_footprint_is_the_rectangle_the_page_draws():
    camera = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 0.75, 64, 64)
    g = facing_gaussians([0.1, 0.2, 0.1], [0.5, 0.9, 0.003])
    areas = footprint_areas(g, camera)
    focal = float(camera.K[0, 0])
    for i, (sigma, opacity) in enumerate([(0.1, 0.5), (0.2, 0.9)]):
        variance = (focal * sigma / 4.0) ** 2 + 0.3  # pixels^2, the 0.3 every footprint gets
        half = math.sqrt(2 * math.log(opacity * 255) * variance) + 0.5  # where alpha reaches 1/255
        assert areas[i].item() == pytest.approx(4 * half * half, rel=1e-4)
    assert areas[2] == 0  # below the cutoff everywhere: not drawn
    behind = Camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 8.0], [0.0, 1.0, 0.0], 0.75, 64, 64)
    assert (footprint_areas(g, behind) == 0).all()


def test_the_ranking_weights_are_the_rasterizer_hits_summed():
    g, _, _ = sphere_of_disks(80)
    cameras = sphere_cameras(3, 24)
    weights, areas = colour_per_pixel(g, cameras)
    expected = torch.zeros(len(g), dtype=torch.float64)
    for camera in cameras:
        ids, _, hit = view_weights(g, camera)
        expected.index_add_(0, ids, hit.double())
    assert torch.allclose(weights, expected, rtol=1e-4, atol=1e-5)
    assert (areas > 0).all()


def test_what_no_view_sees_goes_first_and_the_least_colour_per_pixel_next():
    weights = torch.tensor([5.0, 0.0, 1.0, 0.0, 3.0], dtype=torch.float64)
    areas = torch.tensor([10.0, 0.0, 10.0, 20.0, 10.0], dtype=torch.float64)
    order, shares = drop_order(weights, areas)
    assert order.tolist()[:2] == [1, 3] and order.tolist()[2:] == [2, 4, 0]
    assert torch.allclose(shares, torch.tensor([0.0, 0.4, 0.6, 0.8, 1.0], dtype=torch.float64))
    assert kept(order, shares, 0.0).tolist() == [True, False, True, True, True]
    assert kept(order, shares, 0.65).tolist() == [True, False, False, False, True]


def sphere_with_hidden_haze(surface: int = 600, haze: int = 200) -> Asset:
    """The disk sphere and, inside it, large faint Gaussians no view sees through its opaque shell."""
    g, normals, materials = sphere_of_disks(surface)
    gen = torch.Generator().manual_seed(1)
    inner = Gaussians(
        0.4 * torch.nn.functional.normalize(torch.randn(haze, 3, generator=gen), dim=-1),
        torch.full((haze, 3), 0.3).log(),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(haze, 4).clone(),
        torch.full((haze,), -3.0),
        torch.zeros(haze, 1, 3),
    )
    both = Gaussians(
        *(
            torch.cat([getattr(g, f), getattr(inner, f)])
            for f in ("means", "log_scales", "quats", "opacity_logits", "sh")
        )
    )
    return Asset(both, torch.cat([materials, materials[:haze]]), torch.cat([normals, normals[:haze]]))


def test_the_page_leaves_out_the_hidden_haze_and_keeps_its_psnr():
    asset = sphere_with_hidden_haze()
    view = orbit_spec(sphere_cameras(6, 64), torch.zeros(3), (0.0, 0.0, 1.0))
    light = EnvironmentMap.from_tensor(sky_map(), height=16, learnable=False).prefilter()
    with rendering_with("numba"):  # as `matspray export` on the CPU (the torch reference is ten times slower)
        detail = page_gaussians(asset, view, [light], torch.full((3,), 0.02), min_psnr=40.0)
    assert not detail.keep[600:].any()  # the haze adds nothing to any frame
    # the disks overlap: some go too, and other views of the orbit than the check's stay about as close
    assert detail.keep[:600].float().mean() > 0.5 and detail.psnr >= 40.0 and 0 < detail.left_out < 0.8
    drawn = subset(asset, detail.keep)
    for camera in spec_cameras(page_view(view, 96), 5):
        whole, alpha = render_relit(asset, camera, light, torch.full((3,), 0.02))
        part, _ = render_relit(drawn, camera, light, torch.full((3,), 0.02))
        error = (linear_to_srgb(part) - linear_to_srgb(whole))[alpha > 0.5].square().mean()
        assert -10 * math.log10(error.item()) > 35.0
    every = page_gaussians(asset, view, [light], torch.full((3,), 0.02), min_psnr=math.inf)
    assert every.keep.all() and every.left_out == 0.0


def page_meta(folder) -> dict:
    text = (folder / "asset.js").read_text()
    return json.loads(text[text.index("=") + 1 :].strip().rstrip(";"))["meta"]


@pytest.mark.slow
def test_export_web_draws_what_the_detail_chose_and_refuses_a_psnr_that_is_none(tmp_path, capsys, monkeypatch):
    import matspray.cli.splats as splats_cli
    from matspray.web.page import BUNDLE

    if not BUNDLE.exists():
        pytest.skip(f"the page's script {BUNDLE} is not built (`make setup` builds it with npm)")
    baked, bake = [], splats_cli.bake_light
    monkeypatch.setattr(splats_cli, "bake_light", lambda *a, **k: baked.append(a[0]) or bake(*a, **k))
    run = write_disk_sphere_run(tmp_path, 1500, sphere_cameras(6, 64), slice(None), slice(0, 1))
    assert main(["export", "--run", str(run), "--web", str(tmp_path / "all"), "inf"]) == 0
    every = page_meta(tmp_path / "all")
    assert every["count"] == every["drawnOf"] == 1500
    assert baked == []  # every Gaussian kept: no light prefiltered for a check that is not made
    assert main(["export", "--run", str(run), "--web", str(tmp_path / "some"), "25"]) == 0
    assert baked  # the check's lights
    some = page_meta(tmp_path / "some")
    assert some["drawnOf"] == 1500 and some["count"] < 1500
    assert f"draws {some['count']} of the asset's 1500 Gaussians" in capsys.readouterr().out
    for value in ("0", "-3", "loud"):
        assert main(["export", "--run", str(run), "--web", str(tmp_path / "bad"), value]) == 2
        err = capsys.readouterr().err
        assert f"--web DIR {value}: give the page's PSNR in dB, above 0" in err and err.count("\n") == 1
    assert main(["export", "--run", str(run), "--web", str(tmp_path / "bad"), "30", "40"]) == 2
    assert "--web takes DIR and at most one DB, got 3 values" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
