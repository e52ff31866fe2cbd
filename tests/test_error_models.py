"""The simulated predictor's named error models: each error type is present at the magnitude its
frozen config states, measured on the maps it predicts for a flat synthetic object (one grey base
colour, three roughness bands, no metal; the photo equals the base colour, so nothing is baked in
unless a test puts a highlight there), and its outputs are labelled SIMULATED."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import pytest
import torch

from matspray.cli import main
from matspray.data import Camera, View, load_scene, write_blender, write_image, write_raw
from matspray.errors import ConfigError
from matspray.predictors import make_predictor, predict_views, read_predictor_info
from matspray.predictors.error_models import ERROR_MODELS, SimulationConfig, error_model, model_name
from matspray.predictors.ground_truth import read_ground_truth
from matspray.predictors.maps import MaterialMaps
from matspray.predictors.simulated import (
    BatchDrift,
    SimulatedPredictor,
    ViewOutlier,
    draw_view_outlier,
    filmic_tone,
    simulate_view,
)

VIEWS, SIZE = 120, 12
GREY = 0.4
BANDS = (0.2, 0.6, 1.0)  # roughness of the left, middle and right third
CLIPPED = 0.98658  # std of a standard normal clipped at +-3 (the drift draws are clipped there)


def quiet(_message):
    pass


def neutral_drift() -> BatchDrift:
    """A batch with every drift off, for tests of one effect alone."""
    return BatchDrift(
        exposure=1.0,
        white_balance=[1.0] * 3,
        color_shift=[0.0] * 3,
        roughness_offset=0.0,
        spurious_metallic=0.0,
        shading=0.0,
    )


def flat_object(root, views: int = VIEWS, highlight: bool = False):
    """A `matspray synth`-style folder of `views` flat views;
    with `highlight` the photo is 3x brighter on a 3x3 patch."""
    roughness = torch.tensor(BANDS).repeat_interleave(SIZE // 3).expand(SIZE, SIZE).contiguous()
    basecolor = torch.full((SIZE, SIZE, 3), GREY)
    photo = basecolor.clone()
    if highlight:
        photo[:3, :3] *= 3.0
    train = [
        View(
            f"r_{i:03d}",
            photo,
            None,  # no mask: the whole image is the object
            Camera.look_at([3 * math.cos(i), 3 * math.sin(i), 1.0], [0, 0, 0], [0, 0, 1], math.radians(40), SIZE, SIZE),
        )
        for i in range(views)
    ]
    write_blender(root, {"train": train})
    for view in train:
        write_image(root / "train" / f"{view.name}_basecolor.png", basecolor)
        write_raw(root / "train" / f"{view.name}_roughness.png", roughness, bits=16)
        write_raw(root / "train" / f"{view.name}_metallic.png", torch.zeros(SIZE, SIZE), bits=16)
    return load_scene(root).train


@pytest.fixture(scope="module")
def flat(tmp_path_factory):
    return flat_object(tmp_path_factory.mktemp("flat"))


def predict(views, config: SimulationConfig):
    predictor = SimulatedPredictor(config)
    return predict_views(views, predictor, notify=quiet), predictor.describe()


def log_gains(
    maps, truths
) -> torch.Tensor:  # [V, 3]: per view and channel, log(predicted / tone-mapped true base colour)
    return torch.stack([(m.basecolor / filmic_tone(t.basecolor)).log().mean((0, 1)) for m, t in zip(maps, truths)])


@pytest.mark.parametrize("name", ["paper", "harsh", "outliers"])
def test_per_batch_drift_and_tone_curve_at_their_stated_magnitudes(flat, name):
    config = replace(ERROR_MODELS[name], batch_size=1, seed=11)  # one view per batch: every view is one draw
    out, info = predict(flat, config)
    truths = [read_ground_truth(v) for v in flat]
    casts = {o["view"] for o in info["outliers"] if o["cast"] != [1.0, 1.0, 1.0]}
    keep = [i for i, v in enumerate(flat) if v.name not in casts]
    maps = [out[flat[i].name] for i in keep]
    gains = log_gains(maps, [truths[i] for i in keep])  # [V, 3]
    tone = float(filmic_tone(truths[0].basecolor[0, 0, 0]))
    shift = CLIPPED * config.color_shift_sigma / tone  # the additive shift, as a log gain
    # exposure, white balance, colour shift and the view's own jitter: per channel
    expected = math.sqrt(
        CLIPPED**2 * (config.exposure_sigma**2 + config.white_balance_sigma**2) + config.view_jitter_sigma**2 + shift**2
    )
    assert float(gains.std(0).mean()) == pytest.approx(expected, rel=0.2)
    # white balance and colour shift alone change the hue (channel minus channel mean)
    chroma = gains - gains.mean(1, keepdim=True)
    expected_chroma = math.sqrt(2.0 / 3.0 * (CLIPPED**2 * config.white_balance_sigma**2 + shift**2))
    assert float(chroma.std(0).mean()) == pytest.approx(expected_chroma, rel=0.25)
    # the tone curve darkens the base colour: log gains centre on the curve, not on the truth
    assert math.log(tone / float(truths[0].basecolor[0, 0, 0])) < -0.09
    assert abs(float(gains.mean())) < 3.0 * expected / math.sqrt(len(keep))  # zero-mean drift around the curve
    # roughness: per-batch offset around the tone-mapped value, and [0.2, 1] compressed to the curve's range
    third = SIZE // 3
    middle = torch.stack([m.roughness[:, third : 2 * third].mean() for m in maps]) - filmic_tone(torch.tensor(BANDS[1]))
    expected_rough = math.sqrt(CLIPPED**2 * config.roughness_offset_sigma**2 + config.view_jitter_sigma**2)
    assert float(middle.std()) == pytest.approx(expected_rough, rel=0.2)
    ranges = torch.stack([m.roughness[:, 2 * third :].mean() - m.roughness[:, :third].mean() for m in maps])
    curve = float(filmic_tone(torch.tensor(BANDS[2])) - filmic_tone(torch.tensor(BANDS[0])))
    assert float(ranges.median()) == pytest.approx(curve, abs=0.02) and curve < 0.55 * (BANDS[2] - BANDS[0])


@pytest.mark.parametrize("name", ["paper", "harsh", "outliers"])
def test_spurious_metallic_in_the_stated_fraction_of_batches_and_range(flat, name):
    config = replace(ERROR_MODELS[name], batch_size=1, seed=5)
    out, info = predict(flat, config)
    metal = torch.stack([out[v.name].metallic.mean() for v in flat])  # the object is not metallic at all
    with_metal = metal > 0.01
    assert abs(int(with_metal.sum()) - config.metallic_probability * VIEWS) <= 1
    low, high = config.metallic_amplitude
    assert float(metal[with_metal].min()) >= low - 0.01 and float(metal[with_metal].max()) <= high + 0.01
    assert float(metal[with_metal].mean()) == pytest.approx((low + high) / 2, abs=0.06)
    assert float(metal[~with_metal].max()) == 0.0
    assert [b["spurious_metallic"] > 0 for b in info["batches"]] == with_metal.tolist()  # predictor.json says which


def test_batches_are_consistent_inside_and_differ_between(flat):
    config = replace(ERROR_MODELS["paper"], batch_size=8, seed=2)
    out, _ = predict(flat, config)
    truths = [read_ground_truth(v) for v in flat]
    level = log_gains([out[v.name] for v in flat], truths).mean(1).view(-1, 8)  # [batches, views in batch]
    within = float(((level - level.mean(1, keepdim=True)) ** 2).sum() / (level.numel() - level.shape[0])) ** 0.5
    assert within == pytest.approx(config.view_jitter_sigma, rel=0.25)  # only the view's jitter inside a batch
    assert (
        float(level.mean(1).std()) > 2 * within
    )  # (no batch drift: about within / sqrt(8)) the batch's exposure and white balance between batches


def test_outlier_views_get_a_colour_cast_of_the_stated_size(flat):
    config = replace(ERROR_MODELS["outliers"], seed=3)
    out, info = predict(flat, config)
    plain, _ = predict(flat, replace(config, cast_fraction=0.0))  # the same draws without the casts
    cast_views = [o["view"] for o in info["outliers"] if o["cast"] != [1.0, 1.0, 1.0]]
    assert abs(len(cast_views) - config.cast_fraction * VIEWS) <= 1
    for view in flat:
        ratio = (out[view.name].basecolor / plain[view.name].basecolor).log().mean((0, 1))  # [3]
        if view.name in cast_views:
            assert float(ratio.mean()) == pytest.approx(0.0, abs=0.01)  # a hue shift, not a brightness change
            assert float(ratio.norm()) == pytest.approx(
                config.cast_strength, abs=0.02
            )  # (the additive shift blurs the ratio)
        else:
            assert torch.equal(out[view.name].basecolor, plain[view.name].basecolor)
    assert error_model("paper").cast_fraction == 0.0 and error_model("harsh").cast_fraction == 0.0


def test_baked_highlights_in_the_stated_fraction_of_views_and_amount(tmp_path):
    config = replace(ERROR_MODELS["outliers"], seed=9)
    views = flat_object(tmp_path, views=40, highlight=True)
    out, info = predict(views, config)
    plain, _ = predict(views, replace(config, highlight_fraction=0.0))
    lit = {o["view"] for o in info["outliers"] if o["highlights"] > 0}
    assert len(lit) == round(config.highlight_fraction * 40)
    for view in views:
        changed = (out[view.name].basecolor != plain[view.name].basecolor).any(-1)
        if view.name in lit:
            assert changed[:3, :3].all() and not changed[3:].any() and not changed[:, 3:].any()  # the highlight only
            assert (out[view.name].basecolor[:3, :3] > plain[view.name].basecolor[:3, :3]).all()
        else:
            assert not changed.any()
    # the amount, with every other effect off: base colour moves highlight_amount of the way to white
    neutral = neutral_drift()
    quiet_config = replace(config, tone_strength=0.0, view_jitter_sigma=0.0, blur_fraction=0.0)
    truth = MaterialMaps(torch.full((4, 4, 3), GREY), torch.full((4, 4), 0.5), torch.zeros(4, 4))
    photo = torch.full((4, 4, 3), GREY)
    photo[0, 0] *= 3.0  # twice the median brightness or more: a full highlight
    photo[0, 1] *= 1.5  # half way
    amount = config.highlight_amount
    assert {draw_view_outlier(config, i).highlights for i in range(40)} == {0.0, amount}
    result = simulate_view(truth, photo, None, neutral, quiet_config, 0, ViewOutlier([1.0, 1.0, 1.0], amount)).basecolor
    assert torch.allclose(result[0, 0], torch.full((3,), GREY + amount * (1 - GREY)), atol=1e-5)
    assert torch.allclose(result[0, 1], torch.full((3,), GREY + 0.5 * amount * (1 - GREY)), atol=1e-5)
    assert torch.allclose(result[1:], torch.full((3, 4, 3), GREY), atol=1e-6)


def test_harsh_is_the_paper_model_at_double_severity(flat):
    harsh, _ = predict(flat[:16], error_model("harsh", seed=4))
    doubled, _ = predict(flat[:16], error_model("paper", seed=4, severity=2.0))
    for name in harsh:
        for a, b in zip(
            (harsh[name].basecolor, harsh[name].roughness, harsh[name].metallic),
            (doubled[name].basecolor, doubled[name].roughness, doubled[name].metallic),
        ):
            assert torch.allclose(a, b, atol=1e-5)


def test_named_models_from_the_spec_and_their_labels(flat):
    assert model_name(make_predictor("simulated").config) == "paper"
    assert make_predictor("simulated").config == make_predictor("simulated:paper").config == SimulationConfig()
    for name in ERROR_MODELS:
        info = make_predictor(f"simulated:{name}").describe()
        assert info["simulated"] is True and info["error_model"] == name and "SIMULATED" in info["note"]
    assert model_name(replace(ERROR_MODELS["harsh"], severity=0.5, seed=3, batch_size=2)) == "harsh"
    assert model_name(replace(ERROR_MODELS["harsh"], blur_fraction=0.0)) == "custom"
    with pytest.raises(
        ConfigError, match=r"predictor: 'simulated:nope': unknown error model; use one of paper, harsh, outliers"
    ):
        make_predictor("simulated:nope")
    with pytest.raises(ConfigError, match=r"cast_fraction: must be in \[0, 1\]"):
        SimulationConfig(cast_fraction=2.0)


def test_cli_writes_a_simulated_error_model_labelled_and_refuses_unknown_ones(flat, tmp_path, capsys):
    data = flat[0].path.parent.parent
    run = tmp_path / "run"
    assert (
        main(["predict", "--data", str(data), "--out", str(run), "--predictor", "simulated:outliers", "--seed", "1"])
        == 0
    )
    assert "SIMULATED material maps" in capsys.readouterr().out
    info = read_predictor_info(run)
    assert info["simulated"] is True and info["error_model"] == "outliers" and "SIMULATED" in info["note"]
    assert info["settings"]["cast_fraction"] == ERROR_MODELS["outliers"].cast_fraction and info["settings"]["seed"] == 1
    assert len(info["outliers"]) > 0
    assert main(["predict", "--data", str(data), "--out", str(tmp_path / "bad"), "--predictor", "simulated:wild"]) == 2
    err = capsys.readouterr().err
    assert "unknown error model" in err and "Traceback" not in err
    assert not (tmp_path / "bad" / "materials2d").exists()


def test_another_set_of_views_draws_its_own_errors(flat, tmp_path):
    """Views of the same names in another split folder (the test views) get drifts of their own; the
    same views always get the same maps."""
    config = replace(ERROR_MODELS["paper"], batch_size=8, seed=4)
    first, info = predict(flat[:16], config)
    again, _ = predict(flat[:16], config)
    assert all(torch.equal(first[v.name].roughness, again[v.name].roughness) for v in flat[:16])
    shutil.copytree(flat[0].path.parent, tmp_path / "test")  # the same files, as another split
    other = [replace(v, path=tmp_path / "test" / v.path.name) for v in flat[:16]]
    moved, moved_info = predict(other, config)
    offsets = [b["roughness_offset"] for b in info["batches"]]
    assert offsets != [b["roughness_offset"] for b in moved_info["batches"]]
    assert not torch.equal(first[flat[0].name].roughness, moved[flat[0].name].roughness)
