"""Points triangulated at known cameras for a capture that brings none (matspray.data.triangulate), and the
pipeline's stage `points` that starts the initial Gaussians from them."""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from matspray.data import Camera, View
from matspray.data.formats.blender import write_blender
from matspray.data.images import srgb_to_linear
from matspray.data.scene import MIN_COLMAP_POINTS
from matspray.data.triangulate import PointsConfig, needs_points, neighbour_pairs, points_stage, triangulate_views
from matspray.rundir import RunDir

pytest.importorskip("pycolmap")

HALF = 1.0  # the textured square is [-HALF, HALF]^2 in the plane z = 0


def texture(size: int = 24, seed: int = 0) -> torch.Tensor:  # -> [3, S, S] sRGB blobs, a pattern SIFT finds corners in
    g = torch.Generator().manual_seed(seed)
    return torch.rand(3, size, size, generator=g)


def plane_view(camera: Camera, colours: torch.Tensor, name: str) -> View:
    """A photo of the textured square z = 0 (grey, featureless background elsewhere), ray-traced exactly."""
    cols, rows = torch.meshgrid(torch.arange(camera.width), torch.arange(camera.height), indexing="xy")
    pixels = torch.stack([cols, rows], -1).reshape(-1, 2).float() + 0.5
    origins, dirs = camera.rays_through(pixels)
    t = -origins[:, 2] / dirs[:, 2]
    hit = origins + t[:, None] * dirs  # [R, 3]
    inside = (t > 0) & (hit[:, :2].abs() <= HALF).all(-1)
    grid = (hit[:, :2] / HALF).reshape(1, camera.height, camera.width, 2)
    sampled = torch.nn.functional.grid_sample(colours[None], grid, mode="bilinear", align_corners=False)[0]
    srgb = torch.where(inside.reshape(camera.height, camera.width, 1), sampled.permute(1, 2, 0), torch.tensor(0.5))
    return View(name, srgb_to_linear(srgb), None, camera)


def plane_views(count: int = 8, size: int = 128, colours: torch.Tensor | None = None) -> list[View]:
    colours = texture() if colours is None else colours
    views = []
    for i in range(count):
        azimuth = 2 * math.pi * i / count
        eye = [1.2 * math.cos(azimuth), 1.2 * math.sin(azimuth), 2.5]
        camera = Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1.0, size, size)
        views.append(plane_view(camera, colours, f"r_{i:03d}"))
    return views


def test_points_lie_on_the_true_surface():
    views = plane_views()
    result = triangulate_views(views, PointsConfig(neighbours=4, threads=1))
    assert len(result.points) >= MIN_COLMAP_POINTS, result.message
    assert result.message.startswith(f"triangulated {len(result.points)} points")
    # on the plane z = 0, within a hundredth of its size, and on the square, not the grey background
    assert torch.quantile(result.points[:, 2].abs(), 0.9) < 0.02 * HALF
    assert (result.points[:, :2].abs() < 1.05 * HALF).float().mean() > 0.95
    assert result.colours.shape == result.points.shape and 0 <= result.colours.min() <= result.colours.max() <= 1


def test_sift_starts_at_the_photos_scale_and_doubles_it_only_for_too_few_points(monkeypatch):
    from matspray.data import triangulate

    octaves, lines = [], []
    real = triangulate.extract_sift

    def recording(*args, first_octave, **kwargs):
        octaves.append(first_octave)
        return real(*args, first_octave=first_octave, **kwargs)

    monkeypatch.setattr(triangulate, "extract_sift", recording)
    views, config = plane_views(size=160), PointsConfig(neighbours=4, threads=1)
    once = triangulate_views(views, config, log=lines.append, enough=MIN_COLMAP_POINTS)
    assert octaves == [0] and len(once.points) >= MIN_COLMAP_POINTS, once.message
    assert not any("twice the scale" in line for line in lines)
    octaves.clear()
    twice = triangulate_views(views, config, log=lines.append, enough=len(once.points) + 1)
    assert octaves == [0, -1]  # too few for `enough`: SIFT again from twice the photos' size
    assert any(line.startswith(f"points: {len(once.points)} points from SIFT at the photos' scale") for line in lines)
    assert len(twice.points) > len(once.points)  # the pass with more points is kept: here the doubled scale's
    assert torch.quantile(twice.points[:, 2].abs(), 0.9) < 0.02 * HALF


def test_featureless_photos_give_no_points_and_say_why():
    flat = [View(v.name, torch.full_like(v.image, 0.3), None, v.camera) for v in plane_views(count=4, size=64)]
    result = triangulate_views(flat, PointsConfig(threads=1))
    assert len(result.points) == 0 and result.message == "no features found in the training photos"
    # different textures in every view: features, but no matches that agree with the cameras
    shuffled = [plane_view(v.camera, texture(seed=i), v.name) for i, v in enumerate(plane_views(count=4, size=96))]
    result = triangulate_views(shuffled, PointsConfig(threads=1))
    assert len(result.points) < MIN_COLMAP_POINTS


def test_neighbour_pairs_join_views_near_in_pose():
    views = plane_views(count=8, size=16)
    pairs = neighbour_pairs(views, 2)
    assert all(i < j for i, j in pairs)
    assert {(0, 1), (0, 7), (1, 2)} <= set(pairs)  # neighbours around the ring
    assert (0, 4) not in pairs  # opposite sides
    assert len(neighbour_pairs(views, 100)) == 8 * 7 // 2


class _Scene:
    """What points_stage reads of a scene, and writes back."""

    def __init__(self, views):
        self.train, self.points, self.point_colors = views, None, None
        self.source, self.downscale = None, 1.0


def test_stage_falls_back_in_one_line_and_caches(tmp_path):
    flat = [View(v.name, torch.full_like(v.image, 0.3), None, v.camera) for v in plane_views(count=3, size=48)]
    scene, lines = _Scene(flat), []
    points_stage(RunDir(tmp_path), "fp", scene, PointsConfig(threads=1), False, lines.append)
    assert scene.points is None
    assert lines[-1] == (
        "points: no features found in the training photos; fewer than 100 points, so the initial Gaussians are random "
        "points in the bounds"
    )
    assert (tmp_path / "points" / "points.pt").is_file() and not list((tmp_path / "points").glob("*.tmp*"))


def test_the_stage_gives_back_what_reading_the_photos_freed_before_sift(tmp_path, monkeypatch):
    """malloc_trim between the photos read again and the feature extraction: their freed float images would else stay
    resident under SIFT's threads (docs/dev/real-captures.md, "Packed frozen views")."""
    from matspray.data import triangulate

    calls = []
    monkeypatch.setattr(triangulate, "feature_views", lambda scene, size: calls.append("read") or scene.train)
    monkeypatch.setattr(triangulate, "release_free_memory", lambda: calls.append("trim"))
    monkeypatch.setattr(triangulate, "triangulate_views", lambda *a: calls.append("sift") or triangulate._nothing("-"))
    points_stage(RunDir(tmp_path), "fp", _Scene(plane_views(count=2, size=16)), PointsConfig(), False, lambda _: None)
    assert calls[:3] == ["read", "trim", "sift"]


def test_needs_points_only_for_unmasked_captures_without_points():
    class Bare:
        points, has_masks = None, False

    assert needs_points(Bare(), PointsConfig())
    assert not needs_points(Bare(), PointsConfig(triangulate=False))
    Bare.has_masks = True  # every synthetic scene: left alone, its geometry's fingerprint unchanged
    assert not needs_points(Bare(), PointsConfig())
    Bare.has_masks, Bare.points = False, torch.zeros(500, 3)  # a COLMAP dataset's own points
    assert not needs_points(Bare(), PointsConfig())


def test_pipeline_starts_the_gaussians_from_the_points_and_reuses_them(tmp_path, monkeypatch):
    from matspray.geometry import train as train_module
    from matspray.method import pipeline as pipeline_module
    from matspray.method.config import build_config

    views = plane_views(count=8, size=96)
    data = tmp_path / "capture"
    write_blender(data, {"train": views[:7], "test": views[7:]})
    seen = []
    original = train_module.initial_gaussians

    def recording(scene, *args, **kwargs):
        seen.append(None if scene.points is None else scene.points.clone())
        return original(scene, *args, **kwargs)

    monkeypatch.setattr(train_module, "initial_gaussians", recording)
    enough = []

    def recording_enough(views, config, progress, log, wanted):
        enough.append(wanted)
        return triangulate_views(views, config, progress, log, wanted)

    monkeypatch.setattr("matspray.data.triangulate.triangulate_views", recording_enough)
    settings = {"geometry.iterations": 2, "points.neighbours": 4, "points.threads": 1}
    lines = []
    with pipeline_module.Pipeline(
        data, tmp_path / "run", build_config("test", predictor="none", **settings), progress=False, log=lines.append
    ) as run:
        assert run.plan.points_fp is not None
        assert run.work().points == 7 * 96 * 96  # the estimate counts the feature photos (7 training views)
        run.geometry()
        assert run.work().points == 0.0  # done: no longer counted
    saved = torch.load(tmp_path / "run" / "points" / "points.pt", weights_only=True)
    assert len(saved["points"]) >= MIN_COLMAP_POINTS
    assert seen and seen[0] is not None and torch.equal(seen[0], saved["points"])
    assert any(line.startswith("points: triangulated") for line in lines)
    assert enough == [build_config("test").geometry.init_points]  # the stage triangulates what the Gaussians start from

    def no_second_time(*args, **kwargs):
        raise AssertionError("triangulated again")

    monkeypatch.setattr("matspray.data.triangulate.triangulate_views", no_second_time)
    lines.clear()
    shutil.rmtree(tmp_path / "run" / "geometry")  # the geometry is trained again, on the points made before
    with pipeline_module.Pipeline(
        data, tmp_path / "run", build_config("test", predictor="none", **settings), progress=False, log=lines.append
    ) as run:
        run.geometry()
    assert torch.equal(seen[-1], saved["points"])
    assert any("(reused points/points.pt)" in line for line in lines)


def test_features_come_from_photos_larger_than_the_run_holds(tmp_path):
    from matspray.data import load_scene
    from matspray.data.triangulate import feature_views

    views = plane_views(count=9, size=96)
    write_blender(tmp_path / "capture", {"train": views[:8], "test": views[8:]})
    scene = load_scene(tmp_path / "capture", downscale=None, max_size=48)  # a run's working size
    larger = feature_views(scene, 1024)
    assert [v.name for v in larger] == [v.name for v in scene.train] and larger[0].width == 96
    assert torch.allclose(larger[0].camera.viewmat, scene.train[0].camera.viewmat)
    assert feature_views(load_scene(tmp_path / "capture"), 1024)[0].width == 96  # held at full size: as they are


def test_photos_loaded_again_for_features_are_held_as_8_bit(tmp_path):
    """The points stage holds the photos it loads again as 8-bit sRGB (a quarter of float32: stitch's 110 photos of
    800 x 800 px took 845 MB), the very bytes the feature extractor was given from the float images before."""
    from matspray.data import load_scene
    from matspray.data.triangulate import feature_views, srgb8

    views = plane_views(count=9, size=96)
    write_blender(tmp_path / "capture", {"train": views[:8], "test": views[8:]})
    scene = load_scene(tmp_path / "capture", downscale=None, max_size=48)
    larger = feature_views(scene, 1024)
    full = load_scene(tmp_path / "capture")
    assert all(v.image.dtype == torch.uint8 for v in larger)
    for mine, whole in zip(larger, full.train):
        assert torch.equal(mine.image, srgb8(whole.image))
