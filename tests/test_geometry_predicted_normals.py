"""Gaussian Splatting trained on a 2D model's predicted normals (geometry.predicted_normal_weight, the paper's treatment
of specular objects): the loss term against its definition, the maps brought to the training size, training that
makes the Gaussians' normals truer, the pipeline that feeds the predictions in, and runs made before the setting."""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import pytest
import torch
import torch.nn.functional as F

from matspray.data.scene import Scene
from matspray.errors import SettingError
from matspray.geometry.config import preset
from matspray.geometry.losses import normal_map_loss
from matspray.geometry.normals import depth_normals_along, render_normals, resize_normal_map
from matspray.geometry.step import image_terms
from matspray.geometry.train import load_checkpoint, train_geometry
from matspray.rundir import fingerprint
from matspray.synth.analytic import analytic_views
from tests.test_geometry_step import image_inputs


def test_the_predicted_term_pulls_the_rendered_and_the_depth_normals_over_the_object():
    rgb, alpha, normals, depth, srgb, mask, background, directions, center, predicted = image_inputs(12, 14, 5)
    weights = dict(ssim_weight=0.2, alpha_weight=0.0, normal_weight=0.0)
    both = image_terms(
        rgb, alpha, normals, depth, srgb, mask, background, directions, center, predicted, **weights,
        predicted_weight=0.3, predicted_depth_weight=0.7,
    )  # fmt: skip
    # brute force: alpha eroded by one pixel (min over the 3x3 neighbourhood, edges padded away), times the mask
    padded = F.pad(alpha.detach(), (1, 1, 1, 1), value=float("inf"))
    eroded = torch.stack([padded[i : i + 12, j : j + 14] for i in range(3) for j in range(3)]).amin(0)
    on_object = eroded * (mask > 0.5)
    from_depth = depth_normals_along(depth, directions, center)

    def unsigned(rendered):
        cos = (F.normalize(rendered, dim=-1) * predicted).sum(-1).abs()
        counted = on_object * (predicted.norm(dim=-1) > 0.5)
        return ((1 - cos) * counted).sum() / counted.sum()

    torch.testing.assert_close(both[3], 0.3 * unsigned(normals) + 0.7 * unsigned(from_depth))
    off = image_terms(rgb, alpha, normals, depth, srgb, mask, background, directions, center, predicted, **weights)
    assert float(off[3].detach()) == 0.0
    torch.testing.assert_close(both[[0, 1, 2, 4]], off[[0, 1, 2, 4]])  # the other terms do not move


def test_the_normal_map_loss_has_the_gradient_of_its_formula():
    g = torch.Generator().manual_seed(1)
    rendered = torch.randn(5, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = F.normalize(torch.randn(5, 6, 3, generator=g, dtype=torch.float64), dim=-1)
    target[0] = 0.0  # a row without a prediction
    mask = torch.rand(5, 6, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda r: normal_map_loss(r, target, mask), (rendered,))
    # the same map either way round costs nothing; at right angles it costs 1
    assert float(normal_map_loss(-target, target, torch.ones(5, 6, dtype=torch.float64))) == pytest.approx(0.0)
    side = torch.linalg.cross(target, torch.randn(5, 6, 3, generator=g, dtype=torch.float64), dim=-1)
    assert float(normal_map_loss(side, target, torch.ones(5, 6, dtype=torch.float64))) == pytest.approx(1.0)


def test_a_normal_map_is_brought_to_the_training_size():
    normals = torch.zeros(8, 8, 3)
    normals[:, :6] = F.normalize(torch.tensor([0.0, 0.6, 0.8]), dim=0)
    normals[:, 6:] = 0.0  # no prediction: the right quarter
    normals[:2, :2] = torch.tensor([1.0, 0.0, 0.0])
    small = resize_normal_map(normals, 4, 4)
    assert small.shape == (4, 4, 3)
    # one output pixel = a 2x2 block: mean of its normals, unit again; a block without predictions stays zero
    torch.testing.assert_close(small[0, 0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(small[3, 1], F.normalize(torch.tensor([0.0, 0.6, 0.8]), dim=0))
    assert torch.all(small[:, 3] == 0)
    torch.testing.assert_close(small.norm(dim=-1)[:, :3], torch.ones(4, 3))
    assert resize_normal_map(normals, 8, 8) is normals


def mean_normal_error(gaussians, views, truths) -> float:
    errors = []
    for view, truth in zip(views, truths):
        rendered, alpha = render_normals(gaussians, view.camera)
        inside = (alpha > 0.5) & (view.alpha > 0.5) & (truth.norm(dim=-1) > 0.5)
        cos = (rendered * truth).sum(-1).abs().clamp(max=1.0)
        errors.append(torch.rad2deg(torch.acos(cos))[inside])
    return float(torch.cat(errors).mean())


def test_training_on_true_normals_makes_the_gaussians_normals_truer(tmp_path):
    # the analytic object's exact normals as the "prediction": the trained Gaussians' rendered normals come closer
    # to them than those of the same training without the term (same seed, same views)
    views, truths = analytic_views(8, 32)
    scene = Scene(train=views, test=[], bounds=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    base = preset("test", resolution=32, iterations=150)
    errors = {}
    for weight in (0.0, 1.0):
        config = replace(base, predicted_normal_weight=weight)
        targets = truths if weight > 0 else None
        gaussians = train_geometry(scene, config, tmp_path / f"w{weight}", progress=False, normal_targets=targets)
        errors[weight] = mean_normal_error(gaussians, views, truths)
    assert errors[1.0] < 0.85 * errors[0.0], errors
    assert not math.isnan(errors[1.0])


def test_a_weight_without_normal_maps_is_refused(tmp_path):
    views, _ = analytic_views(2, 16)
    scene = Scene(train=views, test=[], bounds=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    config = replace(preset("test"), predicted_normal_weight=0.5)
    with pytest.raises(SettingError, match="predicted_normal_weight: is 0.5, but no predicted normal maps were given"):
        train_geometry(scene, config, tmp_path, progress=False)
    with pytest.raises(SettingError, match="predicted_normal_weight: must be >= 0"):
        replace(preset("test"), predicted_normal_weight=-1.0)


def test_runs_made_before_the_setting_keep_their_fingerprint_and_checkpoint(tmp_path):
    config = replace(preset("test"), predicted_normal_weight=0.0)  # off, as a run without normal maps trains
    later = ("predicted_normal_weight", "material_edge_threshold", "init")
    before = {k: v for k, v in asdict(config).items() if k not in later}  # the settings then
    assert fingerprint("geometry", "data", config.identity()) == fingerprint("geometry", "data", before)
    on = replace(config, predicted_normal_weight=0.5)
    assert fingerprint("geometry", "data", on.identity()) != fingerprint("geometry", "data", before)
    # a checkpoint written before the setting existed resumes under the setting's off value, not under another
    path = tmp_path / "checkpoint.pt"
    torch.save({"version": 1, "config": before, "iteration": 20, "state": {"x": 1}}, path)
    assert load_checkpoint(path, config) == (20, {"x": 1})
    with pytest.raises(Exception, match="predicted_normal_weight: 0.0 -> 0.5"):
        load_checkpoint(path, on)


def test_the_pipeline_trains_geometry_on_the_predictors_normals(tiny_object, tmp_path):
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    config = build_config("test", predictor="simulated:dr")  # on by default
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lambda _: None) as pipeline:
        work = pipeline.work()  # the estimate before anything ran: the geometry waits on predictions it must not make
        assert work.geometry > 0 and not (tmp_path / "run" / "materials2d").exists()
        targets = pipeline.geometry_normal_targets()
        assert targets is not None and len(targets) == len(pipeline.scene.train)
        # they are the predictor's maps, in world space, on the object
        on_object = targets[0].norm(dim=-1) > 0.5
        assert on_object.float().mean() > 0.05
        torch.testing.assert_close(targets[0][on_object].norm(dim=-1), torch.ones(int(on_object.sum())))
        fp_dr = pipeline.geometry_plan().fingerprint
        pipeline.geometry()
    record = (tmp_path / "run" / "geometry" / "stage.json").read_text()
    assert '"predicted_normal_weight": 1.0' in record
    # another predictor's normals make another geometry
    other = replace(config, predictor_options={**config.predictor_options, "seed": 7})
    with Pipeline(tiny_object, tmp_path / "other", other, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().fingerprint != fp_dr


def test_a_run_without_a_predictor_trains_its_geometry_without_normals(tiny_object, tmp_path):
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    lines = []
    config = build_config("test", predictor="none")
    off = replace(config, geometry=replace(config.geometry, predicted_normal_weight=0.0))
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lines.append) as pipeline:
        assert config.geometry.predicted_normal_weight > 0
        assert pipeline.geometry_plan().settings.predicted_normal_weight == 0.0
        assert pipeline.geometry_normal_targets() is None
        fp = pipeline.geometry_plan().fingerprint
    with Pipeline(tiny_object, tmp_path / "off", off, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().fingerprint == fp  # the geometry of a run made before the default
    assert lines == [] and not (tmp_path / "run" / "materials2d").exists()  # nothing predicted, nothing to say
