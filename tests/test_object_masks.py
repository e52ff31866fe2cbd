"""Captures without masks: the object region (automatic rule and --object-bounds), the masks rendered
from the Gaussians inside it, `synth --background env --ground`, and the pipeline's `masks` stage."""

from __future__ import annotations

import math

import pytest
import torch

from matspray.data import Camera, View
from matspray.data.scene import Scene
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.geometry.region import (
    GROW_LIMIT,
    ObjectRegion,
    auto_region,
    dense_radius,
    framing_radius,
    given_region,
    grown_radius,
    mask_iou,
    regrown,
    support_plane,
)
from matspray.method.masks import (
    compute_object_masks,
    object_alpha,
    read_object_masks,
    read_region,
    write_object_masks,
)
from matspray.render.raster.rasterize import rasterize
from tests.conftest import make_tiny_object, run_cli


def orbit(count: int, distance: float = 4.0, elevation_deg: float = 25.0, size: int = 24) -> list[Camera]:
    z = distance * math.sin(math.radians(elevation_deg))
    ring = distance * math.cos(math.radians(elevation_deg))
    return [
        Camera.look_at([ring * math.cos(a), ring * math.sin(a), z], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.8, size, size)
        for a in (2 * math.pi * i / count for i in range(count))
    ]


def object_on_a_table(seed: int = 0):
    """Points of a ball (radius 0.5 at the origin) resting on a table z = -0.5 (radius 3), and a far shell."""
    g = torch.Generator().manual_seed(seed)
    ball = (
        torch.nn.functional.normalize(torch.randn(3000, 3, generator=g), dim=-1)
        * 0.5
        * torch.rand(3000, 1, generator=g) ** (1 / 3)
    )
    r, a = 3.0 * torch.rand(4000, generator=g).sqrt(), 2 * math.pi * torch.rand(4000, generator=g)
    table = torch.stack(
        [r * torch.cos(a), r * torch.sin(a), torch.full_like(r, -0.5) + 0.01 * torch.randn(4000, generator=g)], -1
    )
    table = table[(table[:, :2].norm(dim=-1) > 0.3)]  # under the ball the table is hidden
    far = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1) * 12.0
    return ball, table, far


def test_automatic_region_keeps_the_object_and_cuts_off_the_table():
    ball, table, far = object_on_a_table()
    points = torch.cat([ball, table, far])
    region = auto_region(points, torch.ones(len(points)), orbit(8))
    assert region.rule == "auto" and region.plane is not None
    normal = torch.tensor(region.plane[:3])
    assert float(normal @ torch.tensor([0.0, 0.0, 1.0])) > 0.99  # the table's normal, facing the cameras
    assert 0.45 <= region.radius <= 0.8
    assert float(region.contains(ball).float().mean()) > 0.9
    assert float(region.contains(table).float().mean()) < 0.01
    assert not region.contains(far).any()


def test_support_plane_needs_every_camera_on_one_side():
    ball, table, _ = object_on_a_table()
    centers = torch.stack([c.center for c in orbit(8)]).double()
    generator = torch.Generator().manual_seed(0)
    far = lambda points: points.norm(dim=-1) > 2.0  # noqa: E731
    assert support_plane(table.double(), centers, 0.08, generator, far(table)) is not None
    straddled = torch.cat([centers, -centers])  # cameras above and below the table: it is not a ground
    assert support_plane(table.double(), straddled, 0.08, generator, far(table)) is None
    flat_top = torch.cat([ball, ball[:1500] * torch.tensor([1.0, 1.0, 0.0]) + torch.tensor([0.0, 0.0, 0.5])])
    assert (
        support_plane(flat_top.double(), centers, 0.08, generator, far(flat_top)) is None
    )  # the object's own face is no ground


@pytest.mark.parametrize("hollow", [False, True])
def test_dense_radius_ends_where_the_density_drops(hollow):
    g = torch.Generator().manual_seed(1)
    # an object of radius 0.7: solid, or a surface (Gaussians sit on surfaces, the inside stays empty)
    core = 0.7 * (0.97 + 0.03 * torch.rand(5000, generator=g) if hollow else torch.rand(5000, generator=g) ** (1 / 3))
    floaters = 3.0 * torch.rand(300, generator=g) ** (1 / 3)  # uniform in the whole reach
    radius = dense_radius(torch.cat([core, floaters]), 3.0)
    assert 0.7 <= radius <= (0.7 + 3.0 / 48) * 1.05 + 1e-6


def test_a_stray_point_near_the_centre_does_not_end_the_region():
    g = torch.Generator().manual_seed(0)
    surface = 0.5 + 0.02 * torch.randn(2000, generator=g)  # an object's surface at 0.5 from the centre
    distances = torch.cat([surface, torch.tensor([0.03])])  # and one Gaussian near the centre, alone in its shell
    assert 0.5 <= dense_radius(distances, 1.2) <= 0.7


def test_framing_radius_is_the_sphere_every_camera_sees_whole():
    cameras = orbit(6, distance=4.0)
    half = math.atan(0.5 * 24 / float(cameras[0].K[0, 0]))
    assert framing_radius(cameras, torch.zeros(3, dtype=torch.float64)) == pytest.approx(4.0 * math.sin(half), rel=1e-5)


def test_given_regions_sphere_box_and_bad_values():
    sphere = given_region([0, 0, 0, 1])
    box = given_region("0 0 0 1 2 3".split())
    points = torch.tensor([[0.5, 0.5, 0.5], [0.9, 0.0, 0.9], [0.5, 1.5, 2.5], [1.5, 0.0, 0.0]])
    assert sphere.contains(points).tolist() == [True, False, False, False]
    assert box.contains(points).tolist() == [True, True, True, False]
    assert box.bounds().tolist() == [[0, 0, 0], [1, 2, 3]]
    for region in (sphere, box, ObjectRegion(center=(1, 2, 3), radius=2.0, plane=(0, 0, 1, 0.5), rule="auto")):
        assert ObjectRegion.from_json(region.to_json()) == region
    for values, message in (
        ([0, 0, 0], "give 4 numbers"),
        ([0, 0, 0, -1], "radius must be > 0"),
        ([0, 0, 0, 1, -1, 1], "first corner must be below"),
        ([0, 0, float("nan"), 1], "finite"),
    ):
        with pytest.raises(SettingError, match=message) as caught:
            given_region(values)
        assert caught.value.setting == "object_bounds"


def test_mask_iou_against_hand_counts():
    a = torch.zeros(4, 4)
    b = torch.zeros(4, 4)
    a[:2, :] = 1  # 8 pixels
    b[1:3, :] = 0.9  # 8 pixels, 4 shared
    assert mask_iou(a, b) == pytest.approx(4 / 12)
    assert mask_iou(torch.zeros(3, 3), torch.zeros(3, 3)) == 1.0


def disks(centers: torch.Tensor, size: float = 0.15) -> Gaussians:
    n = len(centers)
    return Gaussians(
        centers.float(),
        torch.full((n, 3), math.log(size)),
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.full((n,), 5.0),
        torch.zeros(n, 1, 3),
    )


def test_masks_are_the_rendered_alpha_of_the_gaussians_inside(tmp_path):
    g = torch.Generator().manual_seed(2)
    inside_points = 0.4 * torch.randn(200, 3, generator=g)
    outside_points = torch.tensor([[2.2, 0.0, 0.0], [0.0, 2.2, 0.3], [-2.0, -1.0, 0.5]])
    gaussians = disks(torch.cat([inside_points.clamp(-0.9, 0.9), outside_points]))
    cameras = orbit(4)
    views = [View(f"v{i}", torch.zeros(24, 24, 3), None, c) for i, c in enumerate(cameras)]
    scene = Scene(train=views[:3], test=views[3:], bounds=torch.tensor([[-2.0] * 3, [2.0] * 3]))
    masks = compute_object_masks(gaussians, scene, object_bounds=(0, 0, 0, 1.6), progress=False)
    assert masks.inside.tolist() == [True] * 200 + [False] * 3
    obj = gaussians.subset(masks.inside)
    for split in ("train", "test"):
        for view in scene.split(split):
            expected = rasterize(obj, view.camera, torch.zeros(len(obj), 1)).alpha
            assert torch.allclose(masks.masks[split][view.name], expected, atol=1e-6)
    assert torch.equal(object_alpha(obj, cameras[0]), masks.masks["train"]["v0"])
    write_object_masks(tmp_path, masks)
    back = read_object_masks(tmp_path)
    assert back.region == masks.region and torch.equal(back.inside, masks.inside)
    assert (back.masks["test"]["v3"] - masks.masks["test"]["v3"]).abs().max() <= 0.5 / 255 + 1e-6
    assert (tmp_path / "test" / "v3.png").exists()
    back.apply(scene)
    assert all(v.alpha is not None for v in scene.views)
    assert torch.allclose(scene.bounds, torch.tensor([[-1.6] * 3, [1.6] * 3]))


def test_cli_refuses_malformed_object_bounds(tmp_path):
    result = run_cli("run", "--data", tmp_path, "--out", tmp_path / "run", "--object-bounds", "0,0,0")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "--object-bounds: give 4 numbers" in result.stderr


# ------------------------------------------------------------------------------------------ with Mitsuba
@pytest.fixture(scope="module")
def unmasked_object(tmp_path_factory):
    pytest.importorskip("mitsuba")
    return make_tiny_object(tmp_path_factory.mktemp("unmasked") / "data", background="env", ground=True)


def test_synth_photos_show_the_background_and_ground_and_carry_no_mask(unmasked_object):
    import json

    from matspray.data import load_scene
    from matspray.predictors.ground_truth import read_ground_truth_coverage

    scene = load_scene(unmasked_object)
    assert not scene.has_masks and all(v.alpha is None for v in scene.views)
    record = json.loads((unmasked_object / "scene.json").read_text())
    ground = record["photos"]["ground"]
    assert record["photos"]["background"] == "env" and ground is not None
    assert all(float(v.camera.center[2]) > ground["z"] for v in scene.views)  # every camera above the ground
    for view in scene.views:
        coverage = read_ground_truth_coverage(view)
        outside = coverage < 0.01
        assert 0.05 < float(coverage.mean()) < 0.9
        assert float(view.image[outside].mean()) > 0.02  # background and ground are in the photo, not black
    relit = next(unmasked_object.glob("test/*_relight_*.png"))
    from matspray.data.images import read_image

    _, alpha = read_image(relit)
    assert alpha is not None and float(alpha.min()) == 0.0  # the relit truth is the object alone


def test_pipeline_masks_stage_on_an_unmasked_capture(unmasked_object, tmp_path):
    from matspray.eval.run_eval import evaluate_run
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    config = build_config("test", predictor="simulated", **{"refine.iterations": 4})
    run = tmp_path / "run"
    pipeline = Pipeline(unmasked_object, run, config, progress=False, log=lambda _: None)
    pipeline.run_all(("full",))
    masks = read_object_masks(run / "masks")
    assert (run / "masks" / "stage.json").exists() and masks.inside.any()
    focused = read_region(run / "geometry")  # the geometry focused on its object; the masks keep that region,
    assert focused is not None and focused.rule == "auto"  # grown over the trained Gaussians where on a table
    assert (masks.region.center, masks.region.plane) == (focused.center, focused.plane)
    assert masks.region.radius >= focused.radius and (focused.plane is not None or masks.region == focused)
    assert all(v.alpha is not None for v in pipeline.scene.views)  # the masks became the views' alpha
    lift = torch.load(run / "lift" / "projected.pt", weights_only=False)
    assert len(lift["kept"]) == int(masks.inside.sum())  # only the object's Gaussians were lifted
    metrics = evaluate_run(run, progress=False)
    assert 0.0 <= metrics["masks"]["iou_mean"] <= 1.0 and set(metrics["masks"]["views"]) == {"r_000", "r_001"}
    logged = []
    again = Pipeline(unmasked_object, run, config, progress=False, log=logged.append)
    again.run_all(("full",))
    assert logged == ["refine [full]: done before, reusing asset/"]
    again.predict()
    assert "masks: done before, reusing masks/" in logged and "predict: done before, reusing materials2d/" in logged
    given = Pipeline(
        unmasked_object,
        run,
        build_config("test", predictor="simulated", object_bounds=(0, 0, 0, 0.5), **{"refine.iterations": 4}),
        progress=False,
        log=logged.append,
    )
    given.predict()
    assert read_object_masks(run / "masks").region == given_region(
        (0, 0, 0, 0.5)
    )  # a new region: masks and predictions redone
    assert "predict: done before, reusing materials2d/" not in logged[-3:]


# ------------------------------------------------------------------------- an object that fills the frame
def front_cameras(distance: float = 2.5, half_azimuth: float = 60.0, top: float = 45.0) -> list[Camera]:
    """Views of the origin from one side only (-y), elevations 10 to `top` degrees, the NeRF-synthetic lens."""
    cameras = []
    for k in range(12):
        azimuth = math.radians(-90.0 + half_azimuth * (2.0 * ((k * 0.618034) % 1.0) - 1.0))
        elevation = math.radians(10.0 + (top - 10.0) * (k + 0.5) / 12)
        eye = [distance * math.cos(elevation) * math.cos(azimuth), distance * math.cos(elevation) * math.sin(azimuth)]
        cameras.append(Camera.look_at([*eye, distance * math.sin(elevation)], [0, 0, 0], [0, 0, 1], 0.69, 32, 32))
    return cameras


def box_surface(half: float, count: int, g: torch.Generator, faces=range(5)) -> torch.Tensor:
    """Points on the faces of the cube [-half, half]^3: +x, -x, +y, -y, +z (0..4) and -z (5)."""
    points = []
    for face in faces:
        p = (2 * torch.rand(count, 3, generator=g) - 1) * half
        axis, sign = face // 2, 1.0 if face % 2 == 0 else -1.0
        p[:, axis] = sign * half
        points.append(p)
    return torch.cat(points)


def cube_on_a_table(g: torch.Generator):
    """A cube (half 0.6) resting on a table z = -0.6 of which the photos show only a ring around it (out to 1.0, as
    around an object that fills the frame), and a small ball on the table, apart from the cube."""
    cube = box_surface(0.6, 1000, g)
    ring = (2 * torch.rand(6000, 2, generator=g) - 1) * 1.0
    ring = ring[(ring.abs().max(dim=-1).values > 0.62) & (ring.norm(dim=-1) < 1.0)]
    table = torch.cat([ring, torch.full((len(ring), 1), -0.6)], dim=-1)
    ball = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1) * 0.12 + torch.tensor(
        [1.15, 0, -0.45]
    )
    return cube, table, ball


def test_the_region_holds_an_object_that_fills_the_frame_and_leaves_its_table():
    cube, table, ball = cube_on_a_table(torch.Generator().manual_seed(0))
    cameras = front_cameras()
    assert framing_radius(cameras, torch.zeros(3, dtype=torch.float64)) < 0.9  # the cube's corners reach 1.04
    points = torch.cat([cube, table, ball])
    region = auto_region(points, torch.ones(len(points)), cameras)
    assert region.plane is not None and float(torch.tensor(region.plane[:3]) @ torch.tensor([0.0, 0, 1])) > 0.99
    assert float(region.contains(cube[cube[:, 2] > -0.5]).float().mean()) == 1.0  # all of it above the table's cut
    assert not region.contains(table).any()
    assert not region.contains(ball).any()  # on the table beside it, apart from it: not the object


def test_a_face_the_cameras_look_at_is_no_table_but_a_table_around_the_object_is():
    g = torch.Generator().manual_seed(1)
    cube, table, _ = cube_on_a_table(g)
    centers = torch.stack([c.center for c in front_cameras(half_azimuth=30.0, top=30.0)]).double()
    assert (centers[:, 1] < -0.6).all()  # every camera in front of the cube's front face
    seen = box_surface(0.6, 1000, g, faces=(0, 1, 3, 4)).double()  # the faces they see: the sides, front, top
    everywhere = torch.ones(len(seen), dtype=torch.bool)
    nowhere = torch.zeros(len(seen), dtype=torch.bool)
    # every point counted as past the framing sphere: the front face reaches, but the cube is behind it
    assert support_plane(seen, centers, 0.05, torch.Generator().manual_seed(0), nowhere, everywhere) is None
    on_table = torch.cat([seen, table.double()])
    past = torch.cat([nowhere, torch.ones(len(table), dtype=torch.bool)])  # the table's ring is past it
    plane = support_plane(on_table, centers, 0.05, torch.Generator().manual_seed(0), torch.zeros_like(past), past)
    assert plane is not None and plane[2] > 0.99 and abs(float(plane[3]) - 0.6) < 0.05


def test_grown_radius_follows_what_touches_the_core_and_stops_at_its_limit():
    g = torch.Generator().manual_seed(2)
    core = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1) * 0.5
    arm = torch.stack(
        [
            0.5 + 0.3 * torch.rand(800, generator=g),
            0.02 * torch.randn(800, generator=g),
            0.02 * torch.randn(800, generator=g),
        ],
        -1,
    )
    apart = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1) * 0.05 + torch.tensor(
        [0.0, 0.72, 0.0]
    )
    focus = torch.zeros(3, dtype=torch.float64)
    radius = 0.55
    for points, low, high in (
        (core, 0.55, 0.55),
        (torch.cat([core, arm]), 0.78 * 1.05, 0.8 * 1.05),  # the arm, to 0.8, plus 5 %
        (torch.cat([core, apart]), 0.55, 0.55),
    ):
        points = points.double()
        grown = grown_radius(points.norm(dim=-1), points, focus, radius)
        assert low <= grown <= high
    rod = torch.stack([0.5 + 1.9 * torch.rand(3000, generator=g), torch.zeros(3000), torch.zeros(3000)], -1)
    long_arm = torch.cat([core, rod]).double()  # connected all along, out to 2.4: the growth stops at its limit
    assert grown_radius(long_arm.norm(dim=-1), long_arm, focus, radius) == pytest.approx(GROW_LIMIT * radius)


def test_regrown_grows_an_automatic_region_on_a_table_over_the_trained_gaussians_only():
    cube, table, _ = cube_on_a_table(torch.Generator().manual_seed(3))
    cameras = front_cameras()
    points = torch.cat([cube, table])
    early = ObjectRegion(center=(0.0, 0.0, 0.0), radius=0.7, plane=(0.0, 0.0, 1.0, 0.5), rule="auto")
    grown = regrown(early, points, torch.ones(len(points)), cameras)
    assert grown.radius > 1.04 and (grown.center, grown.plane, grown.rule) == (early.center, early.plane, "auto")
    assert float(grown.contains(cube[cube[:, 2] > -0.5]).float().mean()) == 1.0
    for kept in (
        ObjectRegion(center=(0.0, 0.0, 0.0), radius=0.7, plane=(0.0, 0.0, 1.0, 0.5)),  # given
        ObjectRegion(center=(0.0, 0.0, 0.0), radius=0.7, rule="auto"),  # no table: the growth would run along it
    ):
        assert regrown(kept, points, torch.ones(len(points)), cameras) == kept
    faint = regrown(early, points, torch.full((len(points),), 0.1), cameras)  # transparent Gaussians do not count
    assert faint.radius >= 0.7
