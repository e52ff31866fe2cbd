"""Geometry training end to end on a tiny analytic object: it learns, resumes exactly, refuses
mismatched runs; and its CLI."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from matspray.cli import main as cli_main
from matspray.data import load_scene
from matspray.errors import ConfigError, RunError
from matspray.geometry.config import preset
from matspray.geometry.evaluate import evaluate_views
from matspray.geometry.init import initial_gaussians
from matspray.geometry.ply import read_ply
from matspray.geometry.train import prepare_views, train_geometry
from matspray.synth.analytic import write_analytic_dataset


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Training steps are many small ops: on a busy 2-core machine a second thread makes them slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tiny_object(tmp_path_factory):
    """The analytic object, 32 px, 8 training and 3 test views."""
    return write_analytic_dataset(tmp_path_factory.mktemp("object"), train_views=8, test_views=3, resolution=32)


def test_training_raises_test_psnr(tiny_object, tmp_path):
    scene = load_scene(tiny_object)
    config = preset("test", iterations=300)
    initial = initial_gaussians(
        scene,
        prepare_views(scene.train, 40),
        config.init_points,
        config.sh_degree,
        config.init_opacity,
        torch.Generator().manual_seed(0),
        config.init_scale,
    )
    before = evaluate_views(initial, scene.test)
    trained = train_geometry(scene, config, tmp_path / "geometry", progress=False)
    metrics = json.loads((tmp_path / "geometry" / "metrics.json").read_text())
    assert metrics["psnr_masked"] > before["psnr_masked"] + 4, (before["psnr_masked"], metrics["psnr_masked"])
    assert metrics["psnr"] > 24
    assert metrics["normal_error_deg"] < before["normal_error_deg"] - 10
    assert len(trained) != config.init_points  # densification changed the set
    saved, normals = read_ply(tmp_path / "geometry" / "gaussians.ply")
    assert torch.equal(saved.means, trained.means)
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(len(saved)))
    axes = trained.normals()
    torch.testing.assert_close(
        (normals * axes).sum(-1).abs(), torch.ones(len(saved)), atol=1e-5, rtol=0
    )  # ± the shortest axis
    for view in scene.test:
        assert (tmp_path / "geometry" / "renders" / f"{view.name}.png").exists()
        assert (tmp_path / "geometry" / "normals" / f"{view.name}.png").exists()


def test_interrupted_run_resumes_to_the_same_result(tiny_object, tmp_path, monkeypatch):
    scene = load_scene(tiny_object)
    config = replace(
        preset("test"), iterations=40, checkpoint_every=10, densify_from=5, densify_every=10, densify_until=35
    )
    straight = train_geometry(scene, config, tmp_path / "straight", progress=False)

    import matspray.geometry.step as step_module

    original = step_module.training_losses

    def interrupt_at_25(gaussians, view, cfg, iteration, *rest):
        if iteration == 25:
            raise KeyboardInterrupt
        return original(gaussians, view, cfg, iteration, *rest)

    monkeypatch.setattr(step_module, "training_losses", interrupt_at_25)
    with pytest.raises(KeyboardInterrupt):
        train_geometry(scene, config, tmp_path / "resumed", progress=False)
    assert not (tmp_path / "resumed" / "gaussians.ply").exists()
    monkeypatch.setattr(step_module, "training_losses", original)
    resumed = train_geometry(scene, config, tmp_path / "resumed", progress=False)  # continues from iteration 20
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(resumed, name), getattr(straight, name), rtol=0, atol=0)

    again = train_geometry(scene, config, tmp_path / "resumed", progress=False)  # finished: read back, not retrained
    assert torch.equal(again.means, resumed.means)
    with pytest.raises(RunError, match="other geometry settings .*iterations: 40 -> 50.*delete it .*--restart"):
        train_geometry(scene, replace(config, iterations=50), tmp_path / "resumed", progress=False)


def test_cli_writes_the_stage_outputs(tiny_object, tmp_path, capsys):
    code = cli_main(
        [
            "geometry",
            "--data",
            str(tiny_object),
            "--out",
            str(tmp_path / "run"),
            "--preset",
            "test",
            "--set",
            "geometry.iterations=12",
            "--quiet",
        ]
    )
    assert code == 0
    assert (tmp_path / "run" / "geometry" / "gaussians.ply").exists()
    metrics = json.loads((tmp_path / "run" / "geometry" / "metrics.json").read_text())
    assert metrics["iterations"] == 12
    # the PSNR it reports, computed here from what it wrote: each test view's render (PNG, sRGB on white) against
    # the photo in sRGB composited on white by its alpha, -10 log10 of the mean squared error, averaged over views
    from PIL import Image

    from matspray.data import load_scene
    from matspray.rundir import RunDir
    from tests.reference_metrics import srgb

    views = load_scene(tiny_object, downscale=RunDir(tmp_path / "run").downscale()).test
    assert sorted(metrics["views"]) == sorted(view.name for view in views) and views
    values = []
    for view in views:
        render = np.asarray(Image.open(tmp_path / "run" / "geometry" / "renders" / f"{view.name}.png"))[..., :3] / 255.0
        alpha = view.alpha.double().numpy()[..., None]
        target = srgb(view.image.double().numpy()) * alpha + (1.0 - alpha)
        values.append(-10.0 * np.log10(np.mean((render - target) ** 2)))
        assert metrics["views"][view.name]["psnr"] == pytest.approx(values[-1], abs=0.01)  # the PNG's 8-bit rounding
    assert metrics["psnr"] == pytest.approx(np.mean(values), abs=0.01)
    assert "PSNR" in capsys.readouterr().out


def test_cli_reports_bad_input(tmp_path, capsys):
    assert cli_main(["geometry", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "run")]) == 2
    assert "nowhere" in capsys.readouterr().err
    assert (
        cli_main(
            ["geometry", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--set", "geometry.iterations=0"]
        )
        == 2
    )
    assert "--set geometry.iterations: must be >= 1, got 0" in capsys.readouterr().err


def test_presets_and_overrides():
    demo = preset("demo")
    assert demo.resolution == 128 and 20000 <= demo.max_gaussians <= 50000
    assert preset("test").resolution <= 48 and preset("paper").resolution == 512
    short = preset("demo", iterations=300)  # the schedule follows the number of iterations
    assert (
        short.densify_until == demo.densify_until // 10 and short.opacity_reset_every == demo.opacity_reset_every // 10
    )
    with pytest.raises(ConfigError, match="unknown geometry preset 'fast'"):
        preset("fast")
    with pytest.raises(ConfigError, match="sh_degree: must be 0..3"):
        preset("test", sh_degree=4)
    with pytest.raises(ConfigError, match="unknown settings colour"):
        preset("test", colour=1)


def test_unmasked_views_are_scored_over_the_training_background(tmp_path):
    """A photo without a mask is compared whole: where no Gaussian covers it (backdrop no training view saw), the
    render shows what training composited on (black), so a dark backdrop does not turn white."""
    from matspray.data import View
    from matspray.data.images import read_image, srgb_to_linear
    from matspray.geometry.evaluate import render_view
    from tests.scenes import ring_cameras, sphere_of_disks

    gaussians, _, _ = sphere_of_disks(200)
    camera = ring_cameras(1, size=24)[0]
    over_black = render_view(gaussians, camera, 0, torch.zeros(3))
    assert 0.05 < float(over_black.alpha.mean()) < 0.95  # the sphere leaves backdrop in the frame
    photo = srgb_to_linear(over_black.rgb.clamp(0, 1))  # the object before a black backdrop
    unmasked = evaluate_views(gaussians, [View("dark", photo, None, camera)], 0, tmp_path)
    assert unmasked["psnr"] > 50, unmasked
    written, _ = read_image(tmp_path / "renders" / "dark.png")
    assert float(written[over_black.alpha < 1e-3].max()) < 1e-3  # the backdrop written black, not white
    alpha = over_black.alpha
    straight = srgb_to_linear((over_black.rgb / alpha[..., None].clamp_min(1e-4)).clamp(0, 1))  # not premultiplied
    masked = evaluate_views(gaussians, [View("dark", straight * (alpha[..., None] > 0), alpha, camera)], 0)
    assert masked["psnr"] > 50, masked  # with a mask, both sides on white
