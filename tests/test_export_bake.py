"""Textures read from the asset's renders (`bake.view_materials`): a texel takes the material maps the renders show
where it projects, in the views that see it, and nothing from a view where something else is in front of it."""

import numpy as np
import pytest

pytest.importorskip("scipy")

from matspray.export.bake import ViewBake, view_materials  # noqa: E402
from tests.scenes import sphere_cameras, sphere_of_disks  # noqa: E402

RED, BLUE = [0.7, 0.25, 0.2], [0.2, 0.35, 0.7]  # the disk sphere's base colours, by the sign of x


def sphere_directions(count: int = 300, seed: int = 0) -> np.ndarray:  # -> [P, 3] unit, away from x = 0
    directions = np.random.default_rng(seed).normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    return directions[np.abs(directions[:, 0]) > 0.6]


def test_texels_on_the_surface_read_the_rendered_materials_and_hidden_ones_nothing():
    gaussians, _, materials = sphere_of_disks(1500)
    points = sphere_directions()
    # the disks are wide (0.16), so their blended centre depths lie up to about 0.35 off the unit sphere
    views = ViewBake(sphere_cameras(12, 64), depth_tolerance=0.4, min_alpha=0.5)
    values, weight = view_materials(points, points, gaussians, materials, views)
    assert (weight > 0).all()
    expected = np.where(points[:, :1] > 0, RED, BLUE)
    assert np.abs(values[:, :3] - expected).max() < 0.02
    # deep inside the sphere every view's rendered depth is the near surface's: no view sees these points
    _, hidden = view_materials(0.3 * points, points, gaussians, materials, views)
    assert (hidden == 0).all()


def test_one_view_reads_only_the_side_it_sees_weighted_by_how_squarely():
    gaussians, _, materials = sphere_of_disks(1500)
    camera = sphere_cameras(1, 64)[0]
    points = sphere_directions(600)
    towards = points @ (camera.center.numpy() / np.linalg.norm(camera.center.numpy()))  # [P] cosine to the eye
    _, weight = view_materials(points, points, gaussians, materials, ViewBake([camera], 0.4, 0.5))
    assert (weight[towards < 0] == 0).all()
    front = towards > 0.5
    assert front.sum() > 20 and (weight[front] > 0).all()
    # a point seen head-on counts more than one seen at a grazing angle (the cosine from the point to the eye)
    order = np.argsort(towards[front])
    assert weight[front][order[-1]] > weight[front][order[0]]


def test_the_bake_reads_the_views_where_it_is_given_them_and_blends_in_3d_elsewhere():
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("xatlas")
    from matspray.export.atlas import uv_atlas
    from matspray.export.bake import bake_textures, rasterize_uv

    gaussians, _, materials = sphere_of_disks(1500)
    atlas = uv_atlas(trimesh.creation.icosphere(subdivisions=3), 128, 2)

    def bake(views):
        args = (atlas.positions, atlas.faces, atlas.uvs, gaussians, materials.double().numpy(), 128, 16, 0.02)
        return bake_textures(*args, views).reshape(-1, 5)

    in_3d, from_views = bake(None), bake(ViewBake(sphere_cameras(12, 64), 0.4, 0.5))
    assert np.array_equal(bake(ViewBake([], 0.4, 0.5)), in_3d)  # no views: every texel from the Gaussians in 3D
    texels = rasterize_uv(atlas.uvs, atlas.faces, 128)
    points = np.einsum("tk,tkc->tc", texels.bary, atlas.positions[atlas.faces[texels.face]])
    red, blue = points[:, 0] > 0.6, points[:, 0] < -0.6
    for texture in (in_3d, from_views):
        assert np.abs(texture[texels.index[red], :3] - RED).max() < 0.02
        assert np.abs(texture[texels.index[blue], :3] - BLUE).max() < 0.02
    assert np.abs(from_views - in_3d).max() > 0.05  # they differ near the regions' edges


def test_the_export_reads_views_spread_over_the_training_views_when_its_bake_is_views():
    from matspray.export.config import ExportConfig
    from matspray.export.export import BAKE_VIEWS, DEPTH_TOLERANCE_VOXELS, bake_views

    cameras = sphere_cameras(2 * BAKE_VIEWS, 16)
    assert bake_views(cameras, ExportConfig(bake="gaussians"), 0.01) is None
    assert bake_views(cameras, ExportConfig(bake="auto"), 0.01) is None  # unresolved: as gaussians
    views = bake_views(cameras, ExportConfig(bake="views"), 0.01)
    picked = [c.center.tolist() for c in views.cameras]
    assert len(picked) == BAKE_VIEWS and picked[0] == cameras[0].center.tolist()
    assert picked[-1] == cameras[-1].center.tolist()
    assert views.depth_tolerance == pytest.approx(DEPTH_TOLERANCE_VOXELS * 0.01) and views.min_alpha == 0.5
    assert len(bake_views(cameras[:5], ExportConfig(bake="views"), 0.01).cameras) == 5


def test_auto_bakes_from_the_views_for_an_asset_refined_without_the_2d_maps():
    from matspray.errors import SettingError
    from matspray.export.config import ExportConfig
    from matspray.export.export import resolve_bake

    assert resolve_bake(ExportConfig(), "no-prior").bake == "views"
    for variant in ("full", "no-softmax", "proj-average"):
        assert resolve_bake(ExportConfig(), variant).bake == "gaussians"
    assert resolve_bake(ExportConfig(bake="gaussians"), "no-prior").bake == "gaussians"  # a choice stays
    assert resolve_bake(ExportConfig(bake="views"), "full").bake == "views"
    with pytest.raises(SettingError, match="unknown bake 'shiny'; choose one of auto, views, gaussians"):
        ExportConfig(bake="shiny")


def test_camera_in_image_keeps_points_in_front_and_inside_the_frame():
    import torch

    from matspray.data import Camera

    camera = Camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 0.75, 32, 24)
    points = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 8.0], [50.0, 0.0, 0.0], [0.0, -50.0, 0.0], [0.3, 0.2, 1.0]])
    pixels, z = camera.project(points)
    assert camera.in_image(pixels, z).tolist() == [True, False, False, False, True]  # behind; right; below
