"""`matspray synth`: a small object rendered by Mitsuba, its files, and its agreement with the ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")

from matspray.data import load_scene  # noqa: E402
from matspray.data.images import read_image, read_raw  # noqa: E402
from matspray.synth import SynthConfig, make_object  # noqa: E402

SMALL = dict(resolution=32, train_views=3, test_views=2, spp=4, texture_height=64, env_height=32)


@pytest.fixture(scope="module")
def composite(tmp_path_factory):
    out = tmp_path_factory.mktemp("composite")
    result = make_object(SynthConfig(shape="composite", seed=3, **SMALL), out, progress=False, notify=lambda _: None)
    return out, result


def test_writes_every_file_of_the_layout(composite):
    out, result = composite
    assert result.relight_envs == ["studio", "sunset"]
    for split, count in (("train", 3), ("test", 2)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert [f["file_path"] for f in meta["frames"]] == [f"{split}/r_{i:03d}" for i in range(count)]
        assert meta["camera_angle_x"] == pytest.approx(0.6911112, abs=1e-6)
        for i in range(count):
            stem = out / split / f"r_{i:03d}"
            rgba = read_raw(stem.with_suffix(".png"))
            assert rgba.shape == (32, 32, 4)
            assert read_raw(stem.with_name(stem.name + "_basecolor.png")).shape == (32, 32, 3)
            for what in ("roughness", "metallic"):
                assert read_raw(stem.with_name(f"{stem.name}_{what}.png")).shape == (32, 32, 1)
            assert read_raw(stem.with_name(stem.name + "_normal.exr")).shape == (32, 32, 3)
            assert read_raw(stem.with_name(stem.name + "_depth.exr")).shape[:2] == (32, 32)
            if split == "test":
                for env in ("studio", "sunset"):
                    assert read_raw(stem.with_name(f"{stem.name}_relight_{env}.png")).shape == (32, 32, 4)
    for env in ("sky", "studio", "sunset"):
        assert read_raw(out / "envmaps" / f"{env}.exr").shape == (32, 64, 3)
    scene = json.loads((out / "scene.json").read_text())
    assert scene["kind"] == "matspray-synth" and scene["status"] == "complete"
    assert scene["seed"] == 3 and scene["shape"] == "composite" and scene["variant"] == result.variant
    assert scene["lights"] == {"train": "sky", "relight": ["studio", "sunset"]}
    assert scene["settings"]["resolution"] == 32 and len(scene["parts"]) == 4


def test_foundation_reader_loads_the_object(composite):
    out, _ = composite
    scene = load_scene(out)
    assert [v.name for v in scene.train] == ["r_000", "r_001", "r_002"]
    assert [v.name for v in scene.test] == ["r_000", "r_001"]
    assert all(v.alpha is not None and v.alpha.max() > 0.9 for v in scene.views)
    centres = torch.stack([v.camera.center for v in scene.views])
    assert torch.allclose(centres.norm(dim=-1), centres.norm(dim=-1)[:1], atol=1e-4)  # all on one sphere
