"""Photos cut to their object before the working size (matspray.data.crop, matspray.method.crop): the windows
against hand-worked values, the cut views' cameras against the photo's (a world point lands on the same content), the
loader and the run's readers cutting alike, and the pipeline's stage on a capture without masks whose photos are
larger than its working size."""

import math

import pytest
import torch

from matspray.data import Camera, View, load_run_scene, load_scene, write_blender
from matspray.data.crop import CropConfig, CropPlan, crop_window, object_box, read_crop_plan
from matspray.errors import DataError, SettingError
from matspray.geometry.region import ObjectRegion
from matspray.method.crop import plan_crop, read_crop_region
from matspray.method.masks import read_region
from matspray.rundir import RunDir


def test_window_is_the_grown_box_with_the_frames_aspect_moved_inside():
    # a 40 x 20 box centred at (100, 50) of a 200 x 100 frame: grown by 2 x 0.25 -> 60 x 30 px = 0.3 of each side
    window = crop_window(torch.tensor([80.0, 40.0, 120.0, 60.0]), 200, 100, margin=0.25, min_side=0.1)
    assert window == pytest.approx((0.35, 0.35, 0.65, 0.65))
    # the taller side decides (fractions of the frame): 10 x 40 px -> 0.05 and 0.4 of the sides -> 0.4 on both
    assert crop_window(torch.tensor([95.0, 30.0, 105.0, 70.0]), 200, 100, 0.0, 0.1) == pytest.approx(
        (0.3, 0.3, 0.7, 0.7)
    )
    # never below the working size in the photo's pixels
    assert crop_window(torch.tensor([99.0, 49.0, 101.0, 51.0]), 200, 100, 0.0, 0.5) == pytest.approx(
        (0.25, 0.25, 0.75, 0.75)
    )
    # a box at the frame's corner: the window moves inside, keeping its size
    assert crop_window(torch.tensor([0.0, 0.0, 20.0, 10.0]), 200, 100, 0.0, 0.2) == pytest.approx((0, 0, 0.2, 0.2))
    # a box that does not fit, or none: the whole frame
    assert crop_window(torch.tensor([0.0, 0.0, 180.0, 90.0]), 200, 100, 0.1, 0.1) == (0.0, 0.0, 1.0, 1.0)
    assert crop_window(None, 200, 100, 0.1, 0.1) == (0.0, 0.0, 1.0, 1.0)


def test_object_box_holds_the_points_between_its_quantiles():
    camera = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), math.radians(40), 120, 80)
    points = torch.rand(400, 3, generator=torch.Generator().manual_seed(0)) * 0.6 - 0.3
    pixels, _ = camera.project(points)
    box = object_box(points, camera, quantile=0.0)
    assert box.tolist() == pytest.approx([*pixels.min(0).values.tolist(), *pixels.max(0).values.tolist()], abs=1e-3)
    assert object_box(points[:10], camera, 0.0) is None  # too few points to say where the object is
    behind = torch.tensor([[0.0, -6.0, 0.0]]).repeat(50, 1)
    assert object_box(behind, camera, 0.0) is None


def photo(width: int = 160, height: int = 120) -> View:
    """A photo whose every pixel says where it is (red: column, green: row), of a camera looking at the origin."""
    camera = Camera.look_at((0.3, -4.0, 1.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), math.radians(50), width, height)
    rows, cols = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    image = torch.stack([cols / width, rows / height, torch.zeros_like(cols)], -1)
    return View("v", image, None, camera)


def test_a_cut_view_sees_each_world_point_on_the_same_content():
    whole = photo()
    plan = CropPlan(size=(80, 60), windows={"v": (0.25, 0.3, 0.75, 0.8)})
    cut = plan.fit(whole)
    assert (cut.width, cut.height) == (80, 60)
    # the window is pixels 40..120 x 36..96 of the photo, shrunk by 1/0.5 x 1/0.5... to 80 x 60: the same factor
    assert float(cut.camera.K[0, 0]) == pytest.approx(float(whole.camera.K[0, 0]))  # 80 px across 80 px of photo
    points = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.1, -0.1], [-0.15, 0.2, 0.1]])
    in_photo, _ = whole.camera.project(points)
    in_cut, _ = cut.camera.project(points)
    for (x, y), (u, v) in zip(in_photo.tolist(), in_cut.tolist()):
        assert 0 <= u < cut.width and 0 <= v < cut.height
        # what the cut view shows there is what the photo shows at the point: the coordinate the pixel holds
        shown = cut.image[int(v), int(u)]
        assert float(shown[0]) * whole.width == pytest.approx(x, abs=1.0)
        assert float(shown[1]) * whole.height == pytest.approx(y, abs=1.0)
    with pytest.raises(DataError, match="view 'other' has no crop window"):
        plan.fit(View("other", whole.image, None, whole.camera))
    assert CropPlan.from_json(plan.to_json()) == plan


def test_a_cut_and_shrunk_view_keeps_its_content_too():
    whole = photo(320, 240)
    cut = CropPlan(size=(80, 60), windows={"v": (0.1, 0.2, 0.6, 0.7)}).fit(whole)  # 160 x 120 px shrunk to 80 x 60
    points = torch.tensor([[0.1, 0.0, 0.1], [-0.3, 0.1, 0.2]])
    for (x, y), (u, v) in zip(whole.camera.project(points)[0].tolist(), cut.camera.project(points)[0].tolist()):
        shown = cut.image[int(v), int(u)]
        assert float(shown[0]) * whole.width == pytest.approx(x, abs=2.0)
        assert float(shown[1]) * whole.height == pytest.approx(y, abs=2.0)


def test_bad_crop_settings_are_refused_by_name():
    with pytest.raises(SettingError, match="crop.margin"):
        CropConfig(margin=-0.1)
    with pytest.raises(SettingError, match="crop.quantile"):
        CropConfig(quantile=0.5)
    with pytest.raises(SettingError, match="crop.min_gain"):
        CropConfig(min_gain=0.5)


def ring(views: int = 8, size: int = 160) -> list[Camera]:
    cameras = []
    for i in range(views):
        angle = 2 * math.pi * i / views
        eye = (4.0 * math.cos(angle), 4.0 * math.sin(angle), 1.5)
        cameras.append(Camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), math.radians(60), size, size))
    return cameras


def object_points(count: int = 300) -> torch.Tensor:  # a ball of radius 0.4 at the origin
    directions = torch.randn(count, 3, generator=torch.Generator().manual_seed(1))
    return torch.nn.functional.normalize(directions, dim=-1) * 0.4


def test_plan_frames_the_object_and_says_when_it_does_not_cut():
    cameras = ring()
    views = [View(f"v{i}", torch.zeros(80, 80, 3), None, c.resized(80, 80)) for i, c in enumerate(cameras)]
    ball = ObjectRegion(center=(0.0, 0.0, 0.0), radius=0.6)
    points = torch.cat([object_points(), torch.tensor([[3.0, 3.0, 0.0]]).repeat(5, 1)])  # a few points elsewhere
    plan, region, message = plan_crop(views[:6], views[6:], points, 2.0, CropConfig(), (0.0, 0.0, 0.0, 0.6))
    assert region == ball and set(plan.windows) == {v.name for v in views} and plan.size == (80, 80)
    assert "cut to its object" in message
    for view in views:
        window = plan.windows[view.name]
        assert window[2] - window[0] == pytest.approx(window[3] - window[1])  # the frame's aspect
        assert window[2] - window[0] >= 0.5 - 1e-9  # at least the working size in the photo's pixels
        box = object_box(object_points(), view.camera, 0.0) / 80  # the ball, within its window
        assert window[0] <= box[0] and window[1] <= box[1] and box[2] <= window[2] and box[3] <= window[3]
    none, _, why = plan_crop(views[:6], views[6:], points, 1.0, CropConfig(), None)
    assert none is None and "no larger than the working size" in why
    none, _, why = plan_crop(views[:6], views[6:], None, 2.0, CropConfig(), None)
    assert none is None and "no sparse points" in why
    none, _, why = plan_crop(views[:6], views[6:], points, 2.0, CropConfig(enabled=False), None)
    assert none is None and "off" in why
    fills = torch.nn.functional.normalize(torch.randn(300, 3), dim=-1) * 2.0  # an object as large as the frames
    none, _, why = plan_crop(views[:6], views[6:], fills, 2.0, CropConfig(), (0.0, 0.0, 0.0, 2.5))
    assert none is None and "fills most of the photos" in why


@pytest.fixture
def ball_capture(tmp_path):
    """A capture without masks on disk (Blender layout, 160 px photos): a ball of many colours before grey."""
    from matspray.gaussians import Gaussians
    from matspray.render.raster.rasterize import rasterize

    points = object_points(600)
    colours = torch.rand(len(points), 3, generator=torch.Generator().manual_seed(2))
    quats = torch.zeros(len(points), 4)
    quats[:, 0] = 1
    ball = Gaussians(
        points, torch.full((len(points), 3), math.log(0.05)), quats, torch.full((len(points),), 4.0), colours[:, None]
    )
    views = []
    for i, camera in enumerate(ring(10)):
        rendered = rasterize(ball, camera, colours)
        image = rendered.features + 0.5 * (1 - rendered.alpha[..., None])
        views.append(View(f"r_{i:03d}", image.clamp(0, 1).detach(), None, camera))
    write_blender(tmp_path / "data", {"train": views[:8], "test": views[8:]})
    return tmp_path / "data"


def test_the_pipeline_cuts_the_photos_and_every_reader_of_the_run_does_too(ball_capture, tmp_path):
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    config = build_config("test", predictor="none", **{"points.triangulate": False, "geometry.iterations": 40})
    run = tmp_path / "run"
    logged = []
    pipeline = Pipeline(ball_capture, run, config, progress=False, log=logged.append)
    whole = {v.name: v for v in pipeline.scene.views}  # 160 px photos brought to 128 px
    pipeline.scene.points = object_points(400)  # as a capture's structure from motion would give them
    region = pipeline.crop()
    assert region is not None and any("cut to its object" in line for line in logged)
    plan, stored = read_crop_plan(run / "crop"), read_crop_region(run / "crop")
    assert stored == region and set(plan.windows) == set(whole)
    for view in pipeline.scene.views:
        assert (view.width, view.height) == (whole[view.name].width, whole[view.name].height)
        assert float(view.camera.K[0, 0]) > 1.2 * float(whole[view.name].camera.K[0, 0])  # the object larger
    again = load_run_scene(RunDir(run))  # what eval, relight, export and the viewer read
    for view in again.views:
        cut = next(v for v in pipeline.scene.views if v.name == view.name)
        assert torch.equal(view.camera.K, cut.camera.K) and torch.allclose(view.image, cut.image)
    pipeline.geometry()  # trains on the cut photos and focuses on the crop's region
    assert read_region(run / "geometry") == region
    pipeline.object_masks()
    pipeline.close()
    resumed = Pipeline(ball_capture, run, config, progress=False, log=logged.append)
    resumed.object_masks()  # every stage done: the masks reused go onto the cut photos, which stay cut
    resumed.geometry()
    for view in resumed.scene.views:
        cut = next(v for v in pipeline.scene.views if v.name == view.name)
        assert torch.equal(view.camera.K, cut.camera.K) and torch.equal(view.alpha, cut.alpha)
    resumed.close()
    off = Pipeline(ball_capture, tmp_path / "off", build_config("test", predictor="none", **{"crop.enabled": False}))
    off.scene.points = object_points(400)
    assert off.crop() is None and off.plan.crop_fp is None and not (tmp_path / "off" / "crop").exists()
    uncut = load_scene(ball_capture, downscale=pipeline.scene.downscale)
    assert torch.equal(uncut.train[0].camera.K, whole[uncut.train[0].name].camera.K)


def test_an_unreadable_crop_record_is_one_line_naming_it(tmp_path):
    from matspray.errors import MatsprayError

    (tmp_path / "crop.json").write_text('{"plan": {"size": [4]}, "region": null}')
    with pytest.raises(MatsprayError, match=r"crop\.json: is not a crop record .*delete it to cut the photos again"):
        read_crop_plan(tmp_path)
    assert read_crop_region(tmp_path) is None  # the region's entry is null: nothing was cut around one
    assert read_crop_plan(tmp_path / "none") is None  # a run without the stage
