"""`--predictor files:DIR`: every layout on small folders written here, and every bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from matspray.cli import main
from matspray.data import Camera, View, load_scene, write_blender, write_raw
from matspray.errors import ConfigError, DataError
from matspray.predictors import encode_basecolor, make_predictor, predict_views, read_materials2d, read_predictor_info
from matspray.predictors.files import FilesPredictor, detect_layout
from tests.conftest import predict_argv

H, W = 6, 8
COLORS = [(0.8, 0.2, 0.1), (0.1, 0.6, 0.3), (0.2, 0.3, 0.9), (0.5, 0.5, 0.5), (0.9, 0.9, 0.1)]  # linear, one per view
ROUGH = [0.1, 0.35, 0.6, 0.9, 0.5]
METAL = [0.0, 1.0, 0.25, 0.75, 0.5]


def quiet(_message):
    pass


@pytest.fixture
def dataset(tmp_path):
    """Blender-layout dataset with 4 train and 2 test views of 8x6 pixels."""
    views = []
    for i in range(6):
        camera = Camera.look_at([3.0 * np.cos(i), 3.0 * np.sin(i), 0.5], [0, 0, 0], [0, 0, 1], 0.8, W, H)
        views.append(View(f"r_{i:03d}", torch.rand(H, W, 3), None, camera))
    root = tmp_path / "data"
    write_blender(root, {"train": views[:4], "test": views[4:]})
    return root, load_scene(root).train


def constant_maps(i: int, height: int = H, width: int = W):
    return (
        torch.tensor(COLORS[i]).expand(height, width, 3),
        torch.full((height, width), ROUGH[i]),
        torch.full((height, width), METAL[i]),
    )


def assert_constants(maps, names, atol):
    for i, name in enumerate(names):
        m = maps[name]
        assert torch.allclose(m.basecolor, torch.tensor(COLORS[i]).expand(H, W, 3), atol=atol), name
        assert torch.allclose(m.roughness, torch.full((H, W), ROUGH[i]), atol=atol), name
        assert torch.allclose(m.metallic, torch.full((H, W), METAL[i]), atol=atol), name


def write_matspray(folder, names, basecolor_word="basecolor", skip=()):
    for i, name in enumerate(names):
        color, rough, metal = constant_maps(i)
        if (name, "basecolor") not in skip:
            write_raw(folder / f"{name}_{basecolor_word}.png", encode_basecolor(color, "srgb"), bits=16)
        if (name, "roughness") not in skip:
            write_raw(folder / f"{name}_roughness.png", rough, bits=16)
        if (name, "metallic") not in skip:
            write_raw(folder / f"{name}_metallic.png", metal, bits=16)


def write_frames(folder, count, suffix, chunk_size=3, scale=2, encoding="gamma1.8", passes_as_rgb=True):
    """DiffusionRenderer frames {chunk:04d}.{frame:04d}.{pass}.{suffix}, at `scale` times the view size."""
    for i in range(count):
        chunk, frame = divmod(i, chunk_size)
        color, rough, metal = constant_maps(i, H * scale, W * scale)
        stem = folder / f"{chunk:04d}.{frame:04d}"
        write_raw(stem.with_name(stem.name + f".basecolor.{suffix}"), encode_basecolor(color, encoding))
        for name, values in (("roughness", rough), ("metallic", metal)):
            values = values[..., None].expand(-1, -1, 3) if passes_as_rgb else values
            write_raw(stem.with_name(stem.name + f".{name}.{suffix}"), values)
        write_raw(
            stem.with_name(stem.name + f".normal.{suffix}"), torch.rand(H * scale, W * scale, 3)
        )  # other passes are ignored


# ------------------------------------------------------------------------------------------ layouts
@pytest.mark.parametrize("word", ["basecolor", "albedo"])
def test_matspray_layout(dataset, tmp_path, word):
    _, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, [v.name for v in views] + ["r_004"], basecolor_word=word)  # extra maps are ignored
    predictor = make_predictor(f"files:{folder}")
    assert predictor.layout.name == "matspray" and predictor.basecolor_encoding == "srgb"
    assert_constants(predict_views(views, predictor, notify=quiet), [v.name for v in views], atol=1e-4)


def test_diffusionrenderer_svd_layout_maps_frames_in_order_and_resamples(dataset, tmp_path):
    _, views = dataset
    video = tmp_path / "dr" / "object_video"
    video.mkdir(parents=True)
    write_frames(video, 4, "png")  # chunk 0: frames 0-2, chunk 1: frame 0
    predictor = make_predictor(f"files:{tmp_path / 'dr'}")
    assert predictor.layout.name == "diffusionrenderer-svd" and predictor.basecolor_encoding == "gamma1.8"
    notes = []
    maps = predict_views(views, predictor, notify=notes.append)
    assert notes == ["notice: files maps are 16x12, the views 8x6; resampled 4 view(s)"]
    assert_constants(maps, [v.name for v in views], atol=5e-3)  # 8-bit files, gamma 1.8
    assert make_predictor(f"files:{video}").layout.name == "diffusionrenderer-svd"  # the video folder itself works too


def test_diffusionrenderer_cosmos_layout(dataset, tmp_path):
    _, views = dataset
    clip = tmp_path / "cosmos" / "gbuffer_frames" / "object"
    clip.mkdir(parents=True)
    write_frames(clip, 4, "jpg", chunk_size=2, scale=1)
    for root in (tmp_path / "cosmos", tmp_path / "cosmos" / "gbuffer_frames", clip):
        predictor = make_predictor(f"files:{root}")
        assert predictor.layout.name == "diffusionrenderer-cosmos"
    assert_constants(predict_views(views, predictor, notify=quiet), [v.name for v in views], atol=0.02)  # JPEG


def test_frames_of_several_clips_are_taken_in_natural_order(dataset, tmp_path):
    _, views = dataset
    root = tmp_path / "clips" / "gbuffer_frames"
    for clip, indices in (("part10", [2, 3]), ("part9", [0, 1])):  # natural order puts part9 first
        (root / clip).mkdir(parents=True)
        for j, i in enumerate(indices):
            color, rough, metal = constant_maps(i)
            write_raw(root / clip / f"0000.{j:04d}.basecolor.jpg", encode_basecolor(color, "gamma1.8"))
            write_raw(root / clip / f"0000.{j:04d}.roughness.jpg", rough)
            write_raw(root / clip / f"0000.{j:04d}.metallic.jpg", metal)
    notes = []
    predictor = FilesPredictor(tmp_path / "clips", notify=notes.append)
    assert_constants(predict_views(views, predictor, notify=quiet), [v.name for v in views], atol=0.02)
    assert notes == ["notice: frames of 2 clips taken in this order: part9, part10"]


@pytest.mark.parametrize("kind", ["npy", "png"])
def test_marigold_layout(dataset, tmp_path, kind):
    _, views = dataset
    folder = tmp_path / "marigold"
    folder.mkdir()
    for i, view in enumerate(views):
        color, rough, metal = constant_maps(i)
        albedo = encode_basecolor(color, "srgb")
        material = torch.stack([rough, metal, torch.zeros(H, W)], dim=-1)
        if kind == "npy":
            np.save(folder / f"{view.name}_albedo.npy", albedo.numpy())
            np.save(folder / f"{view.name}_material.npy", material.permute(2, 0, 1).numpy())  # CHW, as models save
        else:
            write_raw(folder / f"{view.name}_albedo.png", albedo, bits=16)
            write_raw(folder / f"{view.name}_material.png", material, bits=16)
    predictor = make_predictor(f"files:{folder}")
    assert predictor.layout.name == "marigold"
    assert_constants(predict_views(views, predictor, notify=quiet), [v.name for v in views], atol=1e-4)


def test_basecolor_encoding_option_overrides_the_layout_default(dataset, tmp_path):
    _, views = dataset
    video = tmp_path / "dr" / "v"
    video.mkdir(parents=True)
    write_frames(video, 4, "png", scale=1, encoding="linear")
    predictor = make_predictor(f"files:{tmp_path / 'dr'}", options=_options(basecolor_encoding="linear"))
    assert predictor.basecolor_encoding == "linear"
    assert_constants(predict_views(views, predictor, notify=quiet), [v.name for v in views], atol=5e-3)
    with pytest.raises(ConfigError, match="unknown encoding 'gamma'"):
        make_predictor(f"files:{tmp_path / 'dr'}", options=_options(basecolor_encoding="gamma"))


def _options(**kwargs):
    from matspray.predictors import PredictorOptions

    return PredictorOptions(**kwargs)


# ------------------------------------------------------------------------------------------ bad input
def test_missing_views_are_listed(dataset, tmp_path):
    _, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, ["r_000", "r_001"])
    with pytest.raises(
        DataError,
        match=(
            r"no matspray maps for 2 of 4 views: r_002, r_003 \(maps are matched by view name; "
            r"the folder has maps for r_000, r_001\)"
        ),
    ):
        predict_views(views, make_predictor(f"files:{folder}"), notify=quiet)


def test_incomplete_maps_say_what_is_missing(tmp_path):
    write_matspray(
        tmp_path,
        ["r_000", "r_001", "r_002"],
        skip={("r_001", "metallic"), ("r_002", "metallic"), ("r_000", "basecolor")},
    )
    with pytest.raises(
        DataError, match="incomplete matspray maps: no basecolor for r_000; no metallic for r_001, r_002"
    ):
        make_predictor(f"files:{tmp_path}")


def test_frame_count_must_match_the_views(dataset, tmp_path):
    _, views = dataset
    (tmp_path / "dr").mkdir()
    write_frames(tmp_path / "dr", 3, "png", scale=1)
    with pytest.raises(DataError, match="holds 3 diffusionrenderer-svd frames but there are 4 views"):
        predict_views(views, make_predictor(f"files:{tmp_path / 'dr'}"), notify=quiet)


def test_wrong_channels_and_ranges_are_rejected(dataset, tmp_path):
    _, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, [v.name for v in views])
    write_raw(folder / "r_002_roughness.png", torch.rand(H, W, 3), bits=16)
    with pytest.raises(DataError, match="r_002_roughness.png: is a colour image"):
        predict_views(views, make_predictor(f"files:{folder}"), notify=quiet)
    write_raw(folder / "r_002_roughness.png", torch.rand(H, W), bits=16)
    write_raw(folder / "r_001_basecolor.png", torch.rand(H, W), bits=16)
    with pytest.raises(
        DataError, match="r_001_basecolor.png: is a single-channel image; a base color map needs 3 channels"
    ):
        predict_views(views, make_predictor(f"files:{folder}"), notify=quiet)
    write_raw(folder / "r_001_basecolor.png", torch.rand(H, W, 3), bits=16)
    write_raw(folder / "r_003_metallic.png", torch.rand(H + 1, W), bits=16)
    with pytest.raises(DataError, match="r_003_metallic.png: is 8x7 but its base color r_003_basecolor.png is 8x6"):
        predict_views(views, make_predictor(f"files:{folder}"), notify=quiet)


def test_values_outside_unit_range_are_rejected(dataset, tmp_path):
    _, views = dataset
    for view in views:
        np.save(tmp_path / f"{view.name}_albedo.npy", np.full((H, W, 3), 0.5, np.float32))
        np.save(tmp_path / f"{view.name}_material.npy", np.full((H, W, 3), 0.5, np.float32))
    np.save(tmp_path / "r_001_material.npy", np.full((H, W, 3), 1.5, np.float32))
    with pytest.raises(DataError, match=r"r_001_material.npy: values outside \[0, 1\] \(min 1.5, max 1.5\)"):
        predict_views(views, make_predictor(f"files:{tmp_path}"), notify=quiet)
    np.save(tmp_path / "r_001_material.npy", np.full((H, W, 1), 0.5, np.float32))
    with pytest.raises(DataError, match="r_001_material.npy: has 1 channel\\(s\\); expected roughness, metallic"):
        predict_views(views, make_predictor(f"files:{tmp_path}"), notify=quiet)


def test_undetectable_layout_names_every_layout_tried(tmp_path):
    (tmp_path / "photo.png").write_bytes(b"")
    with pytest.raises(
        DataError,
        match="no known map layout found \\(tried marigold: .*; matspray: .*; "
        "diffusionrenderer-cosmos: .*; diffusionrenderer-svd: .*\\) \\(found photo.png\\)",
    ):
        detect_layout(tmp_path)
    with pytest.raises(DataError, match="nowhere: does not exist"):
        detect_layout(tmp_path / "nowhere")


# ------------------------------------------------------------------------------------------ command line
def test_predict_from_files_writes_materials2d(dataset, tmp_path, capsys):
    root, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, [v.name for v in views])
    run = tmp_path / "run"
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}")) == 0
    assert "wrote maps of 4 train view(s) from the files predictor" in capsys.readouterr().out
    assert_constants(read_materials2d(run, views), [v.name for v in views], atol=1e-4)
    info = read_predictor_info(run)
    assert info["layout"] == "matspray" and info["simulated"] is False and info["views"] == [v.name for v in views]
    # the written folder is itself a MatSpray layout, so it can be a source again
    assert make_predictor(f"files:{run / 'materials2d'}").layout.name == "matspray"


def test_failed_predict_leaves_no_materials2d(dataset, tmp_path, capsys):
    root, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, [v.name for v in views])
    (folder / "r_003_metallic.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(40))  # fails after three good views
    run = tmp_path / "run"
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}")) == 2
    assert "r_003_metallic.png: cannot read image" in capsys.readouterr().err
    assert not (run / "materials2d").exists() and not any(run.glob(".materials2d*"))
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}", "--split", "test")) == 2
    assert "no matspray maps for 2 of 2 views: r_004, r_005" in capsys.readouterr().err


def test_predicting_another_split_into_the_same_run_is_refused(dataset, tmp_path, capsys):
    root, views = dataset
    folder = tmp_path / "maps"
    folder.mkdir()
    write_matspray(folder, [v.name for v in views] + ["r_004"])
    write_raw(folder / "r_005_basecolor.png", torch.rand(H, W, 3))
    write_raw(folder / "r_005_roughness.png", torch.rand(H, W))
    write_raw(folder / "r_005_metallic.png", torch.rand(H, W))
    run = tmp_path / "run"
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}")) == 0
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}")) == 0
    assert "replaced the previous maps" in capsys.readouterr().out
    assert main(predict_argv(root, run, "--predictor", f"files:{folder}", "--split", "test")) == 2
    assert "holds maps of the train split; predicting the test split would replace them" in capsys.readouterr().err
    assert read_predictor_info(run)["split"] == "train"
    assert main(predict_argv(root, tmp_path / "all", "--predictor", f"files:{folder}", "--split", "all")) == 0
    assert read_predictor_info(tmp_path / "all")["views"] == [f"r_{i:03d}" for i in range(6)]


def test_split_all_refuses_views_that_share_names(tmp_path, capsys):
    camera = Camera.look_at([3.0, 0.0, 0.5], [0, 0, 0], [0, 0, 1], 0.8, W, H)
    view = View("r_0", torch.rand(H, W, 3), None, camera)
    write_blender(tmp_path / "data", {"train": [view], "test": [view]})
    assert main(predict_argv(tmp_path / "data", tmp_path / "run", "--predictor", "ground-truth", "--split", "all")) == 2
    assert "train and test views share names (r_0)" in capsys.readouterr().err
