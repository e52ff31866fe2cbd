"""MaterialMaps, base color encodings, the materials2d folder, predict_views and the spec registry."""

from __future__ import annotations

import json

import pytest
import torch

from matspray.data import Camera, View, read_raw, srgb_to_linear, write_raw
from matspray.errors import ConfigError, DataError, SettingError
from matspray.predictors import (
    MaterialMaps,
    Predictor,
    PredictorOptions,
    decode_basecolor,
    encode_basecolor,
    make_predictor,
    predict_views,
    read_materials2d,
    read_predictor_info,
    write_materials2d,
)
from matspray.predictors import maps as maps_module


def make_view(name: str, height: int = 6, width: int = 8) -> View:
    camera = Camera.look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.8, width, height)
    return View(name, torch.rand(height, width, 3), None, camera)


def random_maps(height: int = 6, width: int = 8, confidence: bool = False, seed: int = 0) -> MaterialMaps:
    g = torch.Generator().manual_seed(seed)
    conf = torch.rand(height, width, generator=g) if confidence else None
    return MaterialMaps(
        torch.rand(height, width, 3, generator=g),
        torch.rand(height, width, generator=g),
        torch.rand(height, width, generator=g),
        conf,
    )


# ------------------------------------------------------------------------------------------ encodings
@pytest.mark.parametrize("encoding", ["srgb", "gamma1.8", "linear", "gamma2.2"])
def test_encodings_round_trip(encoding):
    linear = torch.linspace(0.0, 1.0, 300).reshape(-1, 3)
    assert torch.allclose(decode_basecolor(encode_basecolor(linear, encoding), encoding), linear, atol=1e-6)


def test_encodings_match_their_definitions():
    stored = torch.tensor([0.0, 0.02, 0.2, 0.5, 0.9, 1.0])
    assert torch.allclose(decode_basecolor(stored, "gamma1.8"), stored**1.8)
    assert torch.allclose(decode_basecolor(stored, "srgb"), srgb_to_linear(stored))
    assert torch.equal(decode_basecolor(stored, "LINEAR"), stored)
    # the sRGB curve: linear segment below 0.04045, power 2.4 above
    assert float(decode_basecolor(torch.tensor(0.5), "srgb")) == pytest.approx(((0.5 + 0.055) / 1.055) ** 2.4, rel=1e-6)


@pytest.mark.parametrize("bad", ["gamma", "gamma0", "gamma-1", "rec709", ""])
def test_unknown_encoding_is_rejected(bad):
    with pytest.raises(ConfigError, match="basecolor_encoding: unknown encoding"):
        decode_basecolor(torch.zeros(3), bad)


def test_the_cli_names_the_encoding_flag():
    import argparse

    from matspray.cli import build_parser
    from matspray.cli.options import flag_message
    from matspray.predictors.encodings import check_encoding

    with pytest.raises(ConfigError) as caught:
        check_encoding("rec709")
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    message = flag_message(caught.value, "predict", commands["predict"])
    assert message.startswith("--basecolor-encoding: unknown encoding 'rec709'")


# ------------------------------------------------------------------------------------------ MaterialMaps
def test_validate_rejects_bad_maps():
    good = random_maps()
    assert good.validate("x") is good
    with pytest.raises(DataError, match="v1: roughness values outside \\[0, 1\\]"):
        MaterialMaps(good.basecolor, good.roughness + 1.5, good.metallic).validate("v1")
    with pytest.raises(DataError, match="metallic is \\(3, 8\\) but base color is 6x8"):
        MaterialMaps(good.basecolor, good.roughness, torch.zeros(3, 8)).validate("v1")
    with pytest.raises(DataError, match="NaN"):
        MaterialMaps(good.basecolor * float("nan"), good.roughness, good.metallic).validate("v1")
    with pytest.raises(DataError, match="base color must be \\[H, W, 3\\]"):
        MaterialMaps(good.basecolor[..., :2], good.roughness, good.metallic).validate("v1")


def test_resized_keeps_constant_maps_and_changes_size():
    m = MaterialMaps(torch.full((8, 8, 3), 0.25), torch.full((8, 8), 0.5), torch.ones(8, 8), torch.full((8, 8), 0.75))
    r = m.resized(4, 6)
    assert (r.height, r.width) == (4, 6)
    assert torch.allclose(r.basecolor, torch.full((4, 6, 3), 0.25)) and torch.allclose(
        r.confidence, torch.full((4, 6), 0.75)
    )


# ------------------------------------------------------------------------------------------ materials2d folder
def test_materials2d_round_trip_is_accurate(tmp_path):
    views = [make_view("a"), make_view("b")]
    written = {"a": random_maps(confidence=True, seed=1), "b": random_maps(seed=2)}
    folder = write_materials2d(tmp_path / "run", written, {"predictor": "test"})
    names = sorted(p.name for p in folder.iterdir())
    assert names == [
        "a_basecolor.png",
        "a_confidence.png",
        "a_metallic.png",
        "a_roughness.png",
        "b_basecolor.png",
        "b_metallic.png",
        "b_roughness.png",
        "predictor.json",
    ]
    assert read_raw(folder / "a_roughness.png").shape == (6, 8, 1)  # grey 16-bit
    back = read_materials2d(tmp_path / "run", views)
    for name in ("a", "b"):
        assert torch.allclose(back[name].basecolor, written[name].basecolor, atol=2e-4)
        assert torch.allclose(back[name].roughness, written[name].roughness, atol=1e-5)
        assert torch.allclose(back[name].metallic, written[name].metallic, atol=1e-5)
    assert torch.allclose(back["a"].confidence, written["a"].confidence, atol=1e-5) and back["b"].confidence is None
    # base color on disk is sRGB-encoded
    stored = read_raw(folder / "a_basecolor.png")
    assert torch.allclose(srgb_to_linear(stored), written["a"].basecolor, atol=2e-4)
    assert read_predictor_info(tmp_path / "run") == {"predictor": "test", "views": ["a", "b"]}


def test_failed_write_leaves_no_folder_and_keeps_the_previous_one(tmp_path, monkeypatch):
    run = tmp_path / "run"
    maps = {"a": random_maps(), "b": random_maps()}
    real_write = maps_module.write_raw
    calls = []

    def failing_write(path, values, bits=8):
        calls.append(path)
        if len(calls) == 4:
            raise OSError("disk full")
        real_write(path, values, bits=bits)

    monkeypatch.setattr(maps_module, "write_raw", failing_write)
    with pytest.raises(OSError, match="disk full"):
        write_materials2d(run, maps, {"predictor": "first"})
    assert sorted(p.name for p in run.iterdir()) == []  # no materials2d, no temporary folder
    monkeypatch.setattr(maps_module, "write_raw", real_write)
    write_materials2d(run, maps, {"predictor": "first"})
    monkeypatch.setattr(maps_module, "write_raw", failing_write)
    calls.clear()
    with pytest.raises(OSError):
        write_materials2d(run, {"a": random_maps(seed=5), "b": random_maps(seed=6)}, {"predictor": "second"})
    assert sorted(p.name for p in run.iterdir()) == ["materials2d"]
    assert read_predictor_info(run)["predictor"] == "first"
    with pytest.raises(DataError, match="roughness values outside"):  # invalid maps never reach the disk
        write_materials2d(
            run, {"a": MaterialMaps(torch.zeros(2, 2, 3), torch.full((2, 2), 2.0), torch.zeros(2, 2))}, {}
        )
    assert read_predictor_info(run)["predictor"] == "first"


def test_read_materials2d_errors(tmp_path):
    views = [make_view(n) for n in ("a", "b", "c", "d")]
    with pytest.raises(DataError, match="materials2d: does not exist \\(run `matspray predict"):
        read_materials2d(tmp_path, views)
    write_materials2d(tmp_path, {"a": random_maps(), "c": random_maps()}, {})
    with pytest.raises(DataError, match="no maps for 2 of 4 views: b, d"):
        read_materials2d(tmp_path, views)
    with pytest.raises(DataError, match="a_basecolor.png: is 8x6 but view 'a' is 16x12"):
        read_materials2d(tmp_path, [make_view("a", 12, 16)])
    write_raw(tmp_path / "materials2d" / "c_roughness.png", torch.rand(6, 8, 3), bits=16)
    with pytest.raises(DataError, match="c_roughness.png: is a colour image"):
        read_materials2d(tmp_path, [views[2]])
    (tmp_path / "materials2d" / "c_metallic.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(60)))
    write_raw(tmp_path / "materials2d" / "c_roughness.png", torch.rand(6, 8), bits=16)
    with pytest.raises(DataError, match="c_metallic.png: cannot read image"):
        read_materials2d(tmp_path, [views[2]])


# ------------------------------------------------------------------------------------------ predict_views
class FixedPredictor(Predictor):
    name = "fixed"

    def __init__(self, maps):
        self.maps = maps

    def predict(self, views):
        return {v.name: self.maps[v.name] for v in views if v.name in self.maps}


def test_predict_views_resamples_with_one_notice_per_size():
    views = [make_view("a", 6, 8), make_view("b", 6, 8)]
    constant = MaterialMaps(torch.full((12, 12, 3), 0.5), torch.full((12, 12), 0.25), torch.zeros(12, 12))
    notes = []
    out = predict_views(views, FixedPredictor({"a": constant, "b": constant}), notify=notes.append)
    assert list(out) == ["a", "b"] and out["a"].basecolor.shape == (6, 8, 3)
    assert torch.allclose(out["b"].roughness, torch.full((6, 8), 0.25))
    assert notes == [
        "notice: fixed maps are 12x12, the views 8x6; resampled 2 view(s) (aspect ratios differ: "
        "if the model cropped its input, the maps will not line up)"
    ]


def test_predict_views_errors():
    views = [make_view("a"), make_view("b")]
    with pytest.raises(DataError, match="gave no maps for 1 view\\(s\\): b"):
        predict_views(views, FixedPredictor({"a": random_maps()}), notify=print)
    with pytest.raises(DataError, match="repeated: a"):
        predict_views([views[0], views[0]], FixedPredictor({}), notify=print)
    bad = MaterialMaps(torch.zeros(6, 8, 3), torch.full((6, 8), -0.5), torch.zeros(6, 8))
    with pytest.raises(DataError, match="fixed maps of view 'a': roughness values outside"):
        predict_views(views[:1], FixedPredictor({"a": bad}), notify=print)


# ------------------------------------------------------------------------------------------ registry
def test_make_predictor_rejects_bad_specs(tmp_path):
    with pytest.raises(
        ConfigError,
        match=(
            r"unknown predictor 'rgbx'; use one of files:DIR, ground-truth, marigold, "
            r"simulated\[:paper\|harsh\|outliers\|dr\], none"
        ),
    ):
        make_predictor("rgbx")
    with pytest.raises(ConfigError, match="files:DIR needs the folder"):
        make_predictor("files:")
    with pytest.raises(ConfigError, match="ground-truth takes no ':' argument"):
        make_predictor("ground-truth:x")
    with pytest.raises(ConfigError, match="'simulated:x': unknown error model"):
        make_predictor("simulated:x")
    with pytest.raises(
        SettingError, match=r"basecolor_encoding: does not apply to the simulated predictor \(nor do weights\)"
    ):
        make_predictor("simulated", PredictorOptions(weights="w", basecolor_encoding="srgb"))
    with pytest.raises(ConfigError, match="batch_size: must be >= 1"):
        make_predictor("simulated", PredictorOptions(batch_size=0))
    assert make_predictor("simulated", PredictorOptions(severity=0.5, seed=3)).describe()["settings"]["severity"] == 0.5
    assert json.dumps(make_predictor("ground-truth").describe())  # predictor.json must be able to hold it


@pytest.mark.parametrize(
    "content", [b"\x89PNG\r\n\x1a\nshort", b"\x89PNG\r\n\x1a\n" + bytes(range(60)), b"not an image"]
)
def test_corrupt_map_files_give_one_clear_error(tmp_path, content):
    write_materials2d(tmp_path, {"a": random_maps()}, {})
    (tmp_path / "materials2d" / "a_metallic.png").write_bytes(content)
    with pytest.raises(DataError, match="a_metallic.png: cannot read image"):
        read_materials2d(tmp_path, [make_view("a")])


def test_ground_truth_of_another_size_than_the_view_names_the_flag_that_keeps_photos_whole(tmp_path):
    from dataclasses import replace

    from matspray.predictors.ground_truth import read_ground_truth

    view = replace(make_view("r_000", 6, 8), path=tmp_path / "r_000.png")
    write_raw(tmp_path / "r_000_basecolor.png", torch.rand(6, 8, 3))
    for what in ("roughness", "metallic"):
        write_raw(tmp_path / f"r_000_{what}.png", torch.rand(6, 8))
    assert read_ground_truth(view).basecolor.shape == (6, 8, 3)
    shrunk = replace(make_view("r_000", 3, 4), path=view.path)  # the photos brought to a preset's working size
    with pytest.raises(DataError, match=r"r_000_basecolor\.png: is 8x6 but the view is 4x3 .*--downscale 1"):
        read_ground_truth(shrunk)
