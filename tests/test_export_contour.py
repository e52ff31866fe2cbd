"""`export.contour`: the decimated mesh's rim moved onto the asset's silhouettes, vertex by vertex."""

import numpy as np
import pytest
import torch

pytest.importorskip("trimesh")
pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")

import trimesh  # noqa: E402

from matspray.data import Camera  # noqa: E402
from matspray.export.bake import sample_bilinear  # noqa: E402
from matspray.export.contour import contour_offsets, edge_position, faces_near, fit_silhouettes  # noqa: E402
from matspray.export.decimate import decimate  # noqa: E402
from matspray.export.silhouette import mesh_alpha, spread  # noqa: E402
from matspray.export.surface import fuse_surface  # noqa: E402
from tests.scenes import sphere_cameras, sphere_of_disks  # noqa: E402


def coverage(mesh: trimesh.Trimesh, camera: Camera) -> torch.Tensor:  # -> [H, W] share of each pixel covered
    return torch.from_numpy(mesh_alpha(np.asarray(mesh.vertices), np.asarray(mesh.faces), camera, 8)).float()


def sphere(radius: float, subdivisions: int) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def test_the_edge_is_where_a_ramp_crosses_the_level_and_a_line_that_stays_inside_is_not_clean():
    steps = torch.arange(-2.0, 2.0 + 1e-6, 0.125)
    ramp = (0.5 - (steps - 0.3)).clamp(0, 1)  # falls through 0.5 at +0.3 pixels
    covered, empty = torch.ones_like(steps), torch.zeros_like(steps)
    twice = torch.where((steps < -1.0) | ((steps > 0.4) & (steps < 0.9)), 1.0, 0.0)  # leaves at -1 and at 0.9
    beyond = torch.where((steps < -1.0) | (steps > 0.0), 1.0, 0.0)  # ends inside: another part beyond the edge
    offset, clean = edge_position(torch.stack([ramp, covered, empty, twice, beyond]), steps, 0.5)
    assert offset[0].item() == pytest.approx(0.3, abs=1e-5)
    assert clean.tolist() == [True, False, False, True, False]
    assert offset[3].item() == pytest.approx(0.9, abs=0.07)  # of two crossings, the one nearer the middle


def test_a_sphere_a_little_small_grows_onto_the_silhouettes_it_is_shown():
    """Silhouettes of the unit sphere (exact coverage) at 12 cameras pull a sphere of radius 0.96, tessellated
    otherwise, out to radius 1 within a few thousandths (a pixel is ~0.05 units here)."""
    truth, cameras = sphere(1.0, 5), sphere_cameras(12, 64)
    alphas = [coverage(truth, camera) for camera in cameras]
    small = sphere(0.96, 3)
    fitted = fit_silhouettes(small, cameras, alphas, 0.5, rounds=2)
    radius = np.linalg.norm(fitted.vertices, axis=1)
    assert abs(radius.mean() - 1.0) < 0.006 and radius.std() < 0.01
    assert np.array_equal(fitted.faces, small.faces)  # only the positions move
    assert fit_silhouettes(small, cameras, alphas, 0.5, rounds=0) is small


def test_a_view_that_shows_no_edge_near_the_rim_casts_no_vote():
    """Where the asset covers the whole image around the rim (another part in front, or the background's
    Gaussians), or none of it, no vertex is moved by that view; nor by a camera that sees none of the mesh."""
    mesh, camera = sphere(1.0, 3), sphere_cameras(1, 64)[0]
    normals = np.asarray(mesh.vertex_normals)
    for alpha in (torch.ones(64, 64), torch.zeros(64, 64)):
        offsets, voted = contour_offsets(mesh, normals, camera, alpha, 0.5)
        assert not voted.any() and not offsets.any()
    offsets, voted = contour_offsets(mesh, normals, camera, coverage(sphere(1.02, 5), camera), 0.5)
    assert voted.sum() > 20 and (offsets[voted] > 0).mean() > 0.9  # a larger sphere: outwards
    away = Camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 8.0], [0.0, 1.0, 0.0], 0.75, 32, 32)  # sees none of the mesh
    offsets, voted = contour_offsets(mesh, normals, away, torch.zeros(32, 32), 0.5)
    assert not voted.any() and not offsets.any()
    unmoved = fit_silhouettes(mesh, [away], [torch.zeros(32, 32)], 0.5, rounds=2)
    assert np.array_equal(unmoved.vertices, mesh.vertices)


def test_the_fit_brings_a_fused_surface_closer_to_the_asset_in_views_it_was_not_fit_on():
    """The disk sphere's decimated TSDF surface (its level already calibrated to the asset's silhouettes), fit to
    them at 12 cameras: its coverage differs less from the asset's at 6 other cameras than before the fit."""
    gaussians, _, _ = sphere_of_disks(1500)
    cameras, held_out = sphere_cameras(12, 48), sphere_cameras(6, 48, turn=0.9)
    mesh, _, alphas = fuse_surface(gaussians, cameras, 48, 4.0, 0.5, 0.05)
    mesh = decimate(mesh, 3000)
    fitted = fit_silhouettes(mesh, cameras, alphas, 0.5, rounds=2)
    _, _, targets = fuse_surface(gaussians, held_out, 48, 4.0, 0.5, 0.05)

    def mismatch(surface):  # how far the two coverages differ, in pixels, summed over the held-out views
        return sum(float((coverage(surface, c) - t).abs().sum()) for c, t in zip(held_out, targets))

    before, after = mismatch(mesh), mismatch(fitted)
    assert after < 0.9 * before, (before, after)


def test_the_faces_near_the_sampled_points_cover_them_as_all_the_faces_do():
    """Coverage rasterized from `faces_near` alone, read by bilinear taps at the points, equals the whole mesh's;
    and for a few points it is a small part of the faces."""
    mesh, camera = sphere(1.0, 5), sphere_cameras(3, 96)[1]
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    pixels = camera.project(torch.as_tensor(vertices, dtype=torch.float32))[0].numpy()
    points = np.random.default_rng(0).uniform(-2.0, 98.0, size=(40, 2))  # some off the image
    near = faces_near(pixels, faces, points, camera.width, camera.height)
    taps = torch.as_tensor(points, dtype=torch.float32)
    whole, part = (
        sample_bilinear(torch.from_numpy(mesh_alpha(vertices, f, camera, 4))[..., None], taps)
        for f in (faces, faces[near])
    )
    assert torch.equal(whole, part) and 0 < whole.sum() < len(points)  # some points on the sphere, some off it
    assert near.mean() < 0.2


def test_a_round_looks_at_up_to_its_number_of_views_spread_over_all():
    assert spread(96, 48).tolist() == [round(i * 95 / 47) for i in range(48)]
    assert spread(40, 48).tolist() == list(range(40)) and spread(0, 48).tolist() == []
    mesh, cameras = sphere(0.96, 3), sphere_cameras(4, 48)
    alphas = [coverage(sphere(1.0, 5), c) for c in cameras]
    blank = [torch.zeros(48, 48)] * 4  # the asset shows nothing there: no votes
    first_and_last = fit_silhouettes(mesh, cameras, [alphas[0], blank[1], blank[2], alphas[3]], 0.5, 1, views=2)
    assert np.array_equal(first_and_last.vertices, fit_silhouettes(mesh, cameras, alphas, 0.5, 1, views=2).vertices)
    assert not np.array_equal(first_and_last.vertices, fit_silhouettes(mesh, cameras, alphas, 0.5, 1).vertices)
