"""`matspray synth`: a small object rendered by Mitsuba, its files, and its agreement with the ground truth."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("mitsuba")

from matspray.data import load_scene  # noqa: E402
from matspray.data.images import read_raw  # noqa: E402
from matspray.errors import ConfigError, DataError  # noqa: E402
from matspray.synth import SynthConfig, make_object  # noqa: E402

SMALL = dict(resolution=32, train_views=3, test_views=2, spp=32, texture_height=64, env_height=32)
# a sphere at the smallest settings, for the tests of which files are written (not of how they look)
TINY = dict(
    shape="sphere",
    resolution=16,
    train_views=2,
    test_views=1,
    spp=2,
    texture_height=16,
    env_height=16,
    relight_envs=["overcast"],
)


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
            assert read_raw(stem.with_name(stem.name + "_basecolor.png")).shape == (32, 32, 4)
            for what in ("roughness", "metallic"):
                assert read_raw(stem.with_name(f"{stem.name}_{what}.png")).shape == (32, 32, 2)
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


def test_render_alpha_and_ground_truth_coverage_agree(composite):
    out, _ = composite
    for split, count in (("train", 3), ("test", 2)):
        for i in range(count):
            stem = out / split / f"r_{i:03d}"
            alpha = read_raw(stem.with_suffix(".png"))[..., 3]
            base = read_raw(stem.with_name(stem.name + "_basecolor.png"))
            coverage = base[..., 3]
            soft_iou = torch.minimum(alpha, coverage).sum() / torch.maximum(alpha, coverage).sum()
            assert soft_iou > 0.98, (split, i, float(soft_iou))
            disagree = (alpha >= 0.5) != (coverage >= 0.5)  # only edge pixels about half covered may differ
            assert ((coverage[disagree] - 0.5).abs() < 0.3).all(), coverage[disagree]
            assert abs(float((alpha - coverage).mean())) < 0.005  # no shift or scale between the two
            for other in ("roughness", "metallic"):
                assert torch.equal(read_raw(stem.with_name(f"{stem.name}_{other}.png"))[..., 1], coverage)
            depth = read_raw(stem.with_name(stem.name + "_depth.exr"))[..., 0]
            normal = read_raw(stem.with_name(stem.name + "_normal.exr")).norm(dim=-1)
            assert torch.equal(depth > 0, coverage > 0) and torch.equal(normal > 0.5, coverage > 0)
            assert base[..., :3][coverage == 0].abs().max() == 0  # no material outside the object


def test_object_centre_projects_inside_every_mask(composite):
    out, _ = composite
    scene = load_scene(out)
    for view in scene.views:
        pixels, z = view.camera.project(torch.zeros(1, 3))
        x, y = int(pixels[0, 0]), int(pixels[0, 1])
        assert z[0] > 0 and 0 <= x < view.width and 0 <= y < view.height
        assert view.alpha[y - 1 : y + 2, x - 1 : x + 2].max() > 0.5


def test_ground_truth_is_consistent_with_the_render(composite):
    """Where the object is metallic and smooth the render mirrors the sky; where it is rough and
    dielectric it shows its base colour; the depth is the camera distance to the surface."""
    out, _ = composite
    scene = load_scene(out)
    settings = json.loads((out / "scene.json").read_text())
    distance = settings["cameras"]["distance"]
    for view in scene.views:
        depth = read_raw(view.path.with_name(f"{view.name}_depth.exr"))[..., 0]
        inside = depth > 0
        assert depth[inside].min() > distance - 1.2 and depth[inside].max() < distance + 1.2
        normal = read_raw(view.path.with_name(f"{view.name}_normal.exr"))
        to_camera = view.camera.center - torch.zeros(3)
        facing = (normal[inside] @ (to_camera / to_camera.norm())) > -0.05
        assert facing.float().mean() > 0.99  # visible surfaces face the camera
        rough = read_raw(view.path.with_name(f"{view.name}_roughness.png"))[..., 0]
        metal = read_raw(view.path.with_name(f"{view.name}_metallic.png"))[..., 0]
        assert rough[inside].min() >= 0.05 - 1e-3 and rough[inside].max() <= 1.0
        assert metal[inside].min() >= 0.0 and metal[~inside].max() == 0.0


def test_same_arguments_give_the_same_files(tmp_path):
    config = dict(TINY, seed=5)
    first, second = tmp_path / "a", tmp_path / "b"
    make_object(SynthConfig(**config), first, progress=False, notify=lambda _: None)
    make_object(SynthConfig(**config), second, progress=False, notify=lambda _: None)
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert len(files) == 2 * 6 + 1 * 7 + 2 + 3 + 1  # + object.glb
    for name in files:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    # the same arguments again into the same folder are accepted and rewrite the same files
    make_object(SynthConfig(**config), first, progress=False, notify=lambda _: None)
    assert all((first / n).read_bytes() == (second / n).read_bytes() for n in files)


def test_refuses_a_folder_with_a_different_scene_unless_overwrite(tmp_path):
    small = dict(TINY, spp=1)
    make_object(SynthConfig(seed=1, **small), tmp_path, progress=False, notify=lambda _: None)
    with pytest.raises(ConfigError, match="already holds a different `matspray synth` scene.*overwrit"):
        make_object(SynthConfig(seed=2, **small), tmp_path, progress=False, notify=lambda _: None)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="already holds other files"):
        make_object(SynthConfig(seed=2, **small), other, progress=False, notify=lambda _: None)
    make_object(
        SynthConfig(seed=2, overwrite=True, **{**small, "train_views": 1}),
        tmp_path,
        progress=False,
        notify=lambda _: None,
    )
    assert json.loads((tmp_path / "scene.json").read_text())["seed"] == 2
    assert not (tmp_path / "train" / "r_001.png").exists()  # the old scene's extra view is gone
    assert (other / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(shape="cube"), "unknown shape 'cube' .*sphere, rounded-cube, torus, capsule, blob, composite"),
        (dict(env="moon"), "unknown environment map 'moon'.*sky, studio"),
        (dict(relight_envs=["sky", "nowhere.exr"]), "unknown environment map 'nowhere.exr'"),
        (dict(resolution=4), "resolution: must be an integer in \\[8, 2048\\]"),
        (dict(train_views=0), "train_views: must be an integer in \\[1, 1000\\]"),
        (dict(test_views=-1), "test_views: must be"),
        (dict(spp=0), "spp: must be"),
    ],
)
def test_bad_settings_are_refused_before_anything_is_written(tmp_path, changes, message):
    out = tmp_path / "out"
    with pytest.raises(ConfigError, match=message):
        make_object(SynthConfig(**{**SMALL, **changes}), out, progress=False, notify=lambda _: None)
    assert not out.exists()


def test_unreadable_hdr_file_is_a_clear_error(tmp_path):
    broken = tmp_path / "broken.hdr"
    broken.write_bytes(b"not a radiance file")
    with pytest.raises(DataError, match="broken.hdr: cannot read image"):
        make_object(SynthConfig(env=str(broken), **SMALL), tmp_path / "out", progress=False, notify=lambda _: None)


def test_cli_prints_variant_and_one_line_errors(tmp_path, capsys):
    from matspray.cli import main

    code = main(
        [
            "synth",
            "--out",
            str(tmp_path / "o"),
            "--shape",
            "blob",
            "--res",
            "12",
            "--views",
            "1",
            "--test-views",
            "1",
            "--spp",
            "1",
            "--relight-env",
            "studio",
        ]
    )
    printed = capsys.readouterr()
    assert code == 0 and "Mitsuba variant: " in printed.out and "blob under sky" in printed.out
    assert (tmp_path / "o" / "test" / "r_000_relight_studio.png").exists()
    assert main(["synth", "--out", str(tmp_path / "p"), "--shape", "pyramid"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown shape 'pyramid'" in err and "Traceback" not in err
    # --placement places an asset; with a procedural shape it was ignored without a word
    assert main(["synth", "--out", str(tmp_path / "q"), "--shape", "sphere", "--placement", "keep"]) == 2
    err = capsys.readouterr().err
    assert err == "matspray synth: error: --placement is for --asset (a procedural shape has no units)\n"
    assert not (tmp_path / "q").exists()


FALLBACK = """
import json, sys
import matspray.synth.mitsuba_scene as mitsuba_scene
from matspray.synth import SynthConfig, make_object
mitsuba_scene.VARIANTS = ("no_such_variant", "scalar_rgb")
make_object(SynthConfig(**json.loads(sys.argv[2])), sys.argv[1], progress=False)
"""


def test_scalar_variant_fallback_makes_the_same_object(tmp_path):
    """Without a vectorised variant the object is still made (rays traced one by one), and it agrees
    with the vectorised variant's ground truth."""
    import subprocess
    import sys

    settings = dict(TINY, resolution=10, train_views=1, spp=32, gt_samples=2, relight_envs=["studio"])
    done = subprocess.run(
        [sys.executable, "-c", FALLBACK, str(tmp_path / "scalar"), json.dumps(settings)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr
    assert "Mitsuba variant: scalar_rgb" in done.stdout
    make_object(SynthConfig(**settings), tmp_path / "vectorised", progress=False, notify=lambda _: None)
    for name in ("train/r_000_basecolor.png", "train/r_000_roughness.png", "test/r_000_depth.exr"):
        scalar, vectorised = read_raw(tmp_path / "scalar" / name), read_raw(tmp_path / "vectorised" / name)
        assert (scalar - vectorised).abs().max() < 2e-3, name
    relit = [read_raw(tmp_path / v / "test" / "r_000_relight_studio.png") for v in ("scalar", "vectorised")]
    assert abs(float(relit[0][..., 3].mean() - relit[1][..., 3].mean())) < 0.02  # same object size in both
    assert abs(float(relit[0][..., :3].mean() - relit[1][..., :3].mean())) < 0.03  # and about as bright
