"""Ground-truth and simulated predictors, and the multi-view spread, on an analytic sphere object
written in the `matspray synth` layout (true maps, depth and normals next to every view)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from matspray.cli import main
from matspray.data import Camera, View, load_scene, write_blender, write_image, write_raw
from matspray.errors import DataError
from matspray.predictors import make_predictor, predict_views, read_materials2d, read_predictor_info
from matspray.predictors.consistency import backproject, lookup_visible, multiview_spread
from matspray.predictors.ground_truth import GroundTruthPredictor, read_ground_truth, read_ground_truth_depth
from matspray.predictors.simulated import (
    SimulatedPredictor,
    SimulationConfig,
    blur_inside,
    draw_batch_drift,
    filmic_tone,
    shading_ratio,
)
from tests.conftest import predict_argv

LIGHT = torch.tensor([0.3, 0.5, 0.8]) / torch.tensor([0.3, 0.5, 0.8]).norm()


def sphere_materials(
    points: torch.Tensor,
):  # [P, 3] on the unit sphere -> basecolor [P, 3], roughness [P], metallic [P]
    longitude = torch.atan2(points[:, 1], points[:, 0])
    checker = (torch.floor(longitude / (math.pi / 2)) % 2 == 0)[:, None]
    basecolor = torch.where(checker, torch.tensor([0.7, 0.25, 0.1]), torch.tensor([0.1, 0.3, 0.6]))
    roughness = 0.2 + 0.3 * (points[:, 2] + 1.0)
    metallic = (points[:, 0] > 0.5).float()
    return basecolor, roughness, metallic


def sphere_camera(index: int, count: int, size: int) -> Camera:
    angle = 2 * math.pi * index / count
    height = 1.2 * math.sin(3.0 * angle)
    eye = [3.5 * math.cos(angle), 3.5 * math.sin(angle), height]
    return Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(45), size, size)


def render_sphere(camera: Camera):
    """Per pixel: hit mask, camera depth, world normal, true maps, and a Lambert photo (all [H, W, ...])."""
    origins, dirs = camera.rays()
    b = (origins * dirs).sum(-1)
    c = (origins * origins).sum(-1) - 1.0
    disc = b * b - c
    hit = disc > 0
    t = (-b - disc.clamp_min(0).sqrt()).where(hit, torch.zeros_like(b))
    points = origins + t[:, None] * dirs
    normals = points / points.norm(dim=-1, keepdim=True)
    basecolor, roughness, metallic = sphere_materials(normals)
    mask = hit.float()
    shade = 0.1 + (normals @ LIGHT).clamp_min(0)
    photo = (basecolor * shade[:, None] * (1.0 - 0.5 * metallic[:, None])).clamp(0, 1)
    depth = camera.world_to_camera(points)[:, 2] * mask
    H, W = camera.height, camera.width

    def image(x):
        return (x * (mask if x.ndim == 1 else mask[:, None])).reshape(H, W, *x.shape[1:])

    return dict(
        mask=mask.reshape(H, W),
        depth=depth.reshape(H, W),
        normal=image(normals),
        basecolor=image(basecolor),
        roughness=image(roughness),
        metallic=image(metallic),
        photo=image(photo),
    )


def make_sphere_object(root, n_train: int = 6, n_test: int = 2, size: int = 32):
    """A `matspray synth`-style object folder: Blender layout + true maps next to each view."""
    splits = {"train": [], "test": []}
    renders = {}
    count = n_train + n_test
    for i in range(count):
        split = "train" if i < n_train else "test"
        camera = sphere_camera(i, count, size)
        r = render_sphere(camera)
        name = f"r_{i:03d}"
        splits[split].append(View(name, r["photo"], r["mask"], camera))
        renders[(split, name)] = r
    write_blender(root, splits)
    for (split, name), r in renders.items():
        folder = root / split
        write_image(folder / f"{name}_basecolor.png", r["basecolor"])
        write_raw(folder / f"{name}_roughness.png", r["roughness"], bits=16)
        write_raw(folder / f"{name}_metallic.png", r["metallic"], bits=16)
        write_raw(folder / f"{name}_normal.exr", r["normal"])
        write_raw(folder / f"{name}_depth.exr", r["depth"])
    (root / "scene.json").write_text(json.dumps({"kind": "matspray-synth"}))
    return root


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    root = make_sphere_object(tmp_path_factory.mktemp("sphere"))
    return root, load_scene(root)


def quiet(_message):
    pass


# ------------------------------------------------------------------------------------------ ground truth
def test_ground_truth_reads_true_maps(sphere):
    _, scene = sphere
    view = scene.train[0]
    truth = render_sphere(view.camera)
    maps = read_ground_truth(view)
    mask = truth["mask"] > 0
    assert torch.allclose(maps.basecolor[mask], truth["basecolor"][mask], atol=0.01)  # 8-bit sRGB file
    assert torch.allclose(maps.roughness, truth["roughness"], atol=1e-4)  # 16-bit linear
    assert torch.equal(maps.metallic, truth["metallic"])
    assert torch.allclose(read_ground_truth_depth(view), truth["depth"], atol=1e-5)
    out = predict_views(scene.train, GroundTruthPredictor(), notify=quiet)
    assert list(out) == [v.name for v in scene.train]


def test_benchmark_predictors_refuse_data_without_ground_truth(tmp_path):
    camera = sphere_camera(0, 4, 16)
    write_blender(tmp_path, {"train": [View("r_000", torch.rand(16, 16, 3), None, camera)]})
    views = load_scene(tmp_path).train
    for spec in ("simulated", "ground-truth"):
        with pytest.raises(
            DataError, match=r"no ground-truth basecolor/roughness/metallic maps for 1 of 1 views \(r_000\)"
        ):
            predict_views(views, make_predictor(spec), notify=quiet)


# ------------------------------------------------------------------------------------------ simulated effects
def test_severity_zero_is_the_ground_truth(sphere):
    _, scene = sphere
    simulated = predict_views(scene.train, SimulatedPredictor(SimulationConfig(severity=0.0)), notify=quiet)
    for view in scene.train:
        truth = read_ground_truth(view)
        for a, b in zip(
            (truth.basecolor, truth.roughness, truth.metallic),
            (simulated[view.name].basecolor, simulated[view.name].roughness, simulated[view.name].metallic),
        ):
            assert torch.equal(a, b)


def test_simulation_is_seeded_and_inconsistent_across_batches(sphere):
    _, scene = sphere
    config = SimulationConfig(batch_size=3, seed=7)
    first = predict_views(scene.train, SimulatedPredictor(config), notify=quiet)
    again = predict_views(scene.train, SimulatedPredictor(SimulationConfig(batch_size=3, seed=7)), notify=quiet)
    other = predict_views(scene.train, SimulatedPredictor(SimulationConfig(batch_size=3, seed=8)), notify=quiet)
    for name in first:
        assert torch.equal(first[name].basecolor, again[name].basecolor)
        assert torch.equal(first[name].roughness, again[name].roughness)
    assert any(not torch.equal(first[n].basecolor, other[n].basecolor) for n in first)
    truth = {v.name: read_ground_truth(v) for v in scene.train}
    assert all((first[n].basecolor - truth[n].basecolor).abs().max() > 0.01 for n in first)


def test_batches_share_their_colour_drift():
    """With only the per-batch gain on, prediction / truth is one colour per batch, different between batches."""
    config = SimulationConfig(
        batch_size=2,
        seed=3,
        shading_strength=0.0,
        tone_strength=0.0,
        color_shift_sigma=0.0,
        view_jitter_sigma=0.0,
        blur_fraction=0.0,
        metallic_probability=0.0,
    )
    drifts = [draw_batch_drift(config, b) for b in range(3)]
    assert drifts[0] == draw_batch_drift(config, 0)
    assert len({(d.exposure, tuple(d.white_balance)) for d in drifts}) == 3
    from matspray.predictors.maps import MaterialMaps
    from matspray.predictors.simulated import simulate_view

    truth = MaterialMaps(torch.full((4, 4, 3), 0.4), torch.full((4, 4), 0.5), torch.zeros(4, 4))
    photo = torch.full((4, 4, 3), 0.3)
    gains = []
    for index in range(6):
        out = simulate_view(truth, photo, None, drifts[index // 2], config, index)
        gains.append(out.basecolor[0, 0] / 0.4)
        expected = torch.tensor(drifts[index // 2].white_balance) * drifts[index // 2].exposure
        assert torch.allclose(out.basecolor[0, 0] / 0.4, expected.clamp(max=2.5), atol=1e-5)
        assert torch.allclose(
            out.roughness, (0.5 + torch.tensor(drifts[index // 2].roughness_offset)).clamp(0, 1).expand(4, 4), atol=1e-6
        )
    assert torch.equal(gains[0], gains[1]) and not torch.equal(gains[1], gains[2])


def test_a_fraction_of_batches_gets_spurious_metallic():
    for seed in range(5):
        config = SimulationConfig(seed=seed, metallic_probability=0.3)
        metal = [draw_batch_drift(config, b).spurious_metallic > 0 for b in range(10)]
        assert sum(metal) == 3
        assert (
            sum(
                draw_batch_drift(SimulationConfig(seed=seed, metallic_probability=0.3), b).spurious_metallic > 0
                for b in range(5)
            )
            >= 1
        )
    assert not any(draw_batch_drift(SimulationConfig(severity=0.0), b).spurious_metallic for b in range(10))


def test_baked_shading_strength_varies_by_batch_around_its_mean():
    config = SimulationConfig(seed=4)
    exponents = [draw_batch_drift(config, batch).shading for batch in range(400)]
    low, high = (
        config.shading_strength * (1 - config.shading_spread),
        config.shading_strength * (1 + config.shading_spread),
    )
    assert all(low <= e <= high for e in exponents)
    assert abs(sum(exponents) / len(exponents) - config.shading_strength) < 0.03
    assert max(exponents) - min(exponents) > 0.9 * (high - low)  # batches really differ
    flat = SimulationConfig(seed=4, shading_spread=0.0)
    assert {draw_batch_drift(flat, batch).shading for batch in range(5)} == {flat.shading_strength}
    assert draw_batch_drift(SimulationConfig(seed=4, severity=0.0), 3).shading == 0.0
    with pytest.raises(Exception, match="shading_spread: must be in"):
        SimulationConfig(shading_spread=1.5)


def test_effects_change_the_object_only():
    config = SimulationConfig(metallic_probability=1.0, metallic_amplitude=(0.3, 0.3), blur_fraction=0.0)
    from matspray.predictors.maps import MaterialMaps
    from matspray.predictors.simulated import simulate_view

    drift = draw_batch_drift(config, 0)
    assert drift.spurious_metallic == pytest.approx(0.3)
    alpha = torch.zeros(4, 4)
    alpha[:, :2] = 1.0
    truth = MaterialMaps(torch.full((4, 4, 3), 0.4), torch.full((4, 4), 0.5), torch.zeros(4, 4))
    out = simulate_view(truth, torch.full((4, 4, 3), 0.3), alpha, drift, config, 0)
    assert torch.allclose(out.metallic[:, :2], torch.full((4, 2), 0.3)) and torch.equal(
        out.metallic[:, 2:], torch.zeros(4, 2)
    )
    assert torch.equal(out.basecolor[:, 2:], truth.basecolor[:, 2:]) and torch.equal(
        out.roughness[:, 2:], truth.roughness[:, 2:]
    )
    assert not torch.allclose(out.basecolor[:, :2], truth.basecolor[:, :2], atol=0.01)


def test_filmic_tone_darkens_base_color_and_compresses_roughness():
    x = torch.linspace(0.0, 1.0, 101)
    y = filmic_tone(x)
    assert (y[1:] > y[:-1]).all()  # monotonic
    assert float(filmic_tone(torch.tensor(0.18))) == pytest.approx(0.18, abs=2e-3)  # middle grey kept
    assert float(filmic_tone(torch.tensor(1.0))) == pytest.approx(0.6038, abs=2e-3)  # display 0.8 read as sRGB
    assert (y[25:] < x[25:]).all()  # darker above 0.25
    assert (
        float(filmic_tone(torch.tensor(1.0)) - filmic_tone(torch.tensor(0.2))) < 0.55 * 0.8
    )  # roughness range about halved


def test_shading_ratio_recovers_the_shading_of_the_photo():
    basecolor = torch.rand(6, 8, 3) * 0.6 + 0.2
    shading = torch.ones(6, 8)
    shading[:, :4] = 2.0  # lit half twice as bright as the shadowed half
    mask = torch.ones(6, 8, dtype=torch.bool)
    mask[0, 0] = False
    ratio = shading_ratio(basecolor * shading[..., None] * 0.3, basecolor, mask)
    expected = shading / shading[mask].median()
    assert torch.allclose(ratio[mask], expected[mask], rtol=1e-5)
    assert ratio[0, 0] == 1.0


def test_blur_inside_matches_brute_force_normalised_convolution():
    torch.manual_seed(0)
    x = torch.rand(7, 9, 2, dtype=torch.float64)
    weight = (torch.rand(7, 9, dtype=torch.float64) > 0.3).double()
    sigma = 0.8
    out = blur_inside(x, weight, sigma)
    radius = math.ceil(3 * sigma)
    offsets = range(-radius, radius + 1)
    g = {d: math.exp(-0.5 * (d / sigma) ** 2) for d in offsets}
    expected = x.clone()
    for i in range(7):
        for j in range(9):
            num, den = torch.zeros(2, dtype=torch.float64), 0.0
            for di in offsets:
                for dj in offsets:
                    ii, jj = min(max(i + di, 0), 6), min(max(j + dj, 0), 8)  # replicate border
                    num += g[di] * g[dj] * weight[ii, jj] * x[ii, jj]
                    den += g[di] * g[dj] * float(weight[ii, jj])
            blurred = num / max(den, 1e-6 * sum(g.values()) ** 2)
            expected[i, j] = weight[i, j] * blurred + (1 - weight[i, j]) * x[i, j]
    assert torch.allclose(out, expected, atol=1e-9)
    assert torch.allclose(blur_inside(torch.full((5, 5, 1), 0.3), torch.ones(5, 5), 1.0), torch.full((5, 5, 1), 0.3))


# ------------------------------------------------------------------------------------------ multi-view spread
def test_backproject_then_project_returns_the_pixel_centres(sphere):
    _, scene = sphere
    view = scene.train[1]
    depth = read_ground_truth_depth(view)
    points = backproject(view.camera, depth)
    rows, cols, visible = lookup_visible(view.camera, depth, points, 1e-4)
    expected_rows, expected_cols = torch.nonzero(depth > 0, as_tuple=True)
    assert visible.all() and torch.equal(rows, expected_rows) and torch.equal(cols, expected_cols)
    assert torch.allclose(points.norm(dim=-1), torch.ones(len(points), dtype=torch.float64), atol=1e-4)  # on the sphere


def test_spread_of_true_maps_is_near_zero_and_of_view_offsets_matches_analytic_visibility(sphere):
    _, scene = sphere
    views = scene.train
    cameras = [v.camera for v in views]
    depths = [read_ground_truth_depth(v) for v in views]
    truth = [read_ground_truth(v).roughness[..., None] for v in views]
    spread = multiview_spread(cameras, depths, truth)
    assert spread.points > 1000 and float(spread.per_channel[0]) < 0.01
    # every view sees a constant of its own: a point's spread is the std over the views that see it
    constants = torch.tensor([0.1, 0.9, 0.3, 0.5, 0.7, 0.2], dtype=torch.float64)
    flat = [torch.full_like(d, float(c))[..., None] for d, c in zip(depths, constants)]
    measured = multiview_spread(cameras, depths, flat, points_per_view=10**6)
    stds = []
    for source, (camera, depth) in enumerate(zip(cameras, depths)):
        points = backproject(camera, depth)
        normals = points / points.norm(dim=-1, keepdim=True)
        seen = []
        for target in cameras:  # a convex sphere: visible iff facing the camera and inside the frame
            pixels, z = target.project(points)
            inside = (
                (z > 0)
                & (pixels[:, 0] >= 0)
                & (pixels[:, 1] >= 0)
                & (pixels[:, 0] < target.width)
                & (pixels[:, 1] < target.height)
            )
            facing = ((target.center.double() - points) * normals).sum(-1) > 0
            seen.append(inside & facing)
        seen = torch.stack(seen).double()  # [V, P]
        n = seen.sum(0)
        keep = n >= 2
        mean = (constants[:, None] * seen).sum(0) / n.clamp_min(1)
        std = (((constants[:, None] - mean) ** 2 * seen).sum(0) / n.clamp_min(1)).sqrt()
        stds.append(std[keep])
    reference = torch.cat(stds).mean()
    assert float(measured.per_channel[0]) == pytest.approx(float(reference), rel=0.05)


# ------------------------------------------------------------------------------------------ command line
def test_predict_simulated_and_ground_truth_through_the_cli(sphere, tmp_path, capsys):
    root, scene = sphere
    run = tmp_path / "run"
    assert main(predict_argv(root, run, "--predictor", "simulated", "--batch-size", "2", "--seed", "5")) == 0
    printed = capsys.readouterr().out
    assert "SIMULATED" in printed
    info = read_predictor_info(run)
    assert info["simulated"] is True and "SIMULATED" in info["note"] and info["settings"]["seed"] == 5
    assert [b["views"] for b in info["batches"]] == [["r_000", "r_001"], ["r_002", "r_003"], ["r_004", "r_005"]]
    maps = read_materials2d(run, scene.train)
    expected = predict_views(scene.train, SimulatedPredictor(SimulationConfig(batch_size=2, seed=5)), notify=quiet)
    for name, m in maps.items():
        assert torch.allclose(m.roughness, expected[name].roughness, atol=1e-4)
        assert torch.allclose(m.basecolor, expected[name].basecolor, atol=1e-3)
    copied = tmp_path / "copied"  # maps read back from a simulated run stay labelled as simulated
    assert main(predict_argv(root, copied, "--predictor", f"files:{run / 'materials2d'}")) == 0
    assert "SIMULATED" in capsys.readouterr().out
    info = read_predictor_info(copied)
    assert info["simulated"] is True and info["source_predictor"]["predictor"] == "simulated"
    run = tmp_path / "evaluation"
    assert main(predict_argv(root, run, "--predictor", "ground-truth", "--split", "test")) == 0
    assert "GROUND-TRUTH" in capsys.readouterr().out
    info = read_predictor_info(run)
    assert (
        info["predictor"] == "ground-truth" and info["benchmark_only"] is True and info["views"] == ["r_006", "r_007"]
    )


def test_cli_rejects_options_that_do_not_apply(sphere, tmp_path, capsys):
    root, _ = sphere
    code = main(predict_argv(root, tmp_path / "run", "--predictor", "ground-truth", "--severity", "2"))
    assert code == 2
    assert "--severity: does not apply to the ground-truth predictor" in capsys.readouterr().err
    assert not (tmp_path / "run" / "materials2d").exists()
    assert main(predict_argv(root, tmp_path / "run", "--predictor", "simulated", "--severity", "-1")) == 2
    assert "--severity: must be a number >= 0" in capsys.readouterr().err
    # marigold's own flags are named as the user typed them (they read '--set seed', '--set processing_resolution')
    for flag in ("--seed", "--processing-resolution"):
        assert main(predict_argv(root, tmp_path / "run", "--predictor", "ground-truth", flag, "64")) == 2
        assert f"error: {flag}: does not apply to the ground-truth predictor" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ benchmark
def load_benchmark():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "predictors.py"
    spec = importlib.util.spec_from_file_location("benchmark_predictors", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_benchmark_pieces_and_report(sphere, capsys):
    bench = load_benchmark()
    mask = torch.tensor([[True, False]])
    assert bench.psnr(torch.tensor([[[0.5], [0.0]]]), torch.tensor([[[0.6], [1.0]]]), mask) == pytest.approx(20.0)
    assert bench.psnr(torch.zeros(1, 2, 1), torch.zeros(1, 2, 1), mask) == math.inf
    assert bench.mean_psnr([20.0, math.inf, 30.0]) == (25.0, 1)
    root, scene = sphere
    assert bench.main(["--data", str(root), "--batch-size", "2"]) == 0
    out = capsys.readouterr().out
    truth_row = next(line for line in out.splitlines() if line.startswith("ground-truth"))
    simulated_row = next(line for line in out.splitlines() if line.startswith("simulated (severity 1)"))
    assert truth_row.split()[1:4] == ["inf", "inf", "inf"]
    truth_spread = [float(x) for x in truth_row.split()[-3:]]
    simulated_spread = [float(x) for x in simulated_row.split()[-3:]]
    assert (
        max(truth_spread) < 0.02
        and simulated_spread[0] > 2 * truth_spread[0]
        and simulated_spread[1] > 2 * truth_spread[1]
    )
    assert bench.main(["--data", str(root / "missing")]) == 2
    assert "matspray synth" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------ one draw per object
def test_a_simulated_predictor_without_a_seed_draws_from_the_objects_own_seed(sphere, tmp_path):
    """The objects of a benchmark (synth seeds 0, 1, ...) have views of the same names; without this
    every object would get the same batches of spurious metallic, outliers and drifts."""
    import shutil

    from matspray.predictors import PredictorOptions, options_for_dataset

    root, _ = sphere
    copies = {}
    for seed in (0, 5):
        copy = tmp_path / f"seed{seed}"
        shutil.copytree(root, copy)
        (copy / "scene.json").write_text(json.dumps({"kind": "matspray-synth", "seed": seed}))
        copies[seed] = copy
    assert options_for_dataset("simulated", PredictorOptions(), copies[5]).seed == 5
    assert options_for_dataset("simulated:outliers", PredictorOptions(), copies[5]).seed == 5
    assert options_for_dataset("simulated", PredictorOptions(seed=2), copies[5]).seed == 2  # a given seed wins
    assert options_for_dataset("ground-truth", PredictorOptions(), copies[5]).seed is None
    assert options_for_dataset("simulated", PredictorOptions(), root).seed is None  # scene.json without a seed
    assert options_for_dataset("simulated", PredictorOptions(), tmp_path).seed is None  # no scene.json

    def predicted(data, *flags):
        run = tmp_path / f"run-{data.name}{''.join(flags)}"
        assert main(predict_argv(data, run, "--predictor", "simulated", *flags)) == 0
        return read_materials2d(run, load_scene(data).train)

    object0, object5, forced = predicted(copies[0]), predicted(copies[5]), predicted(copies[0], "--seed", "5")
    default = predicted(copies[0], "--seed", "0")  # the error model's default seed
    for name in object0:
        assert torch.equal(object0[name].basecolor, default[name].basecolor)  # object seed 0: the default draws
        assert torch.equal(object5[name].basecolor, forced[name].basecolor)  # object seed 5: as --seed 5
    assert any(not torch.equal(object0[n].basecolor, object5[n].basecolor) for n in object0)
