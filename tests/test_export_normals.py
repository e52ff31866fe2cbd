"""The exported mesh's per-vertex normals: the surface's own (smoothed), the Gaussians' refined normals, and the
mix of the two that `--asset-normals` sets."""

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("xatlas")
pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")

from matspray.data.loader import load_run_scene  # noqa: E402
from matspray.export.bake import blend_normals  # noqa: E402
from matspray.export.config import ExportConfig  # noqa: E402
from matspray.export.export import mesh_from_asset, run_asset  # noqa: E402
from matspray.export.normals import angle_degrees  # noqa: E402
from matspray.method.asset import read_asset  # noqa: E402
from matspray.rundir import RunDir  # noqa: E402
from tests.scenes import sphere_cameras, write_disk_sphere_run  # noqa: E402


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_blend_normals_flips_each_gaussian_to_the_surface_side_then_mixes_at_the_share():
    reference = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # [P, 3] the surface's own
    tilted = unit(np.array([1.0, 0.0, 1.0]))  # 45 degrees off the reference
    normals = np.stack([tilted, -tilted, np.array([1.0, 0.0, 0.0])])  # [N, 3]; the second is the first, flipped
    ids = np.array([[0, 1], [2, 2]])
    weights = np.array([[0.5, 0.5], [1.0, 0.0]])
    # point 0: the two flipped to one side agree; point 1: a normal at 90 degrees, taken as it is
    assert np.allclose(blend_normals(ids, weights, normals, reference, 1.0), [tilted, [1.0, 0.0, 0.0]])
    assert np.allclose(blend_normals(ids, weights, normals, reference, 0.0), reference)
    half = blend_normals(ids, weights, normals, reference, 0.5)
    assert np.allclose(angle_degrees(half, reference), [22.5, 45.0])  # the bisector of the two
    assert np.allclose(np.linalg.norm(half, axis=-1), 1.0)
    # normals that cancel after the flips (a sheet seen edge-on) leave the surface's own
    edge = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    flat = np.array([[0.0, 1.0, 0.0]])
    assert np.allclose(blend_normals(np.array([[0, 1]]), np.array([[0.5, 0.5]]), edge, flat, 1.0), flat)


@pytest.fixture(scope="module")
def disk_meshes(tmp_path_factory):
    """The disk sphere's run exported at the Gaussians' shares 0, 0.5 and 1 (small settings): {share: mesh}."""
    run = write_disk_sphere_run(
        tmp_path_factory.mktemp("disks"), 1500, sphere_cameras(12, 40), slice(None), slice(0, 2)
    )
    asset = read_asset(run_asset(run, "full"))
    cameras = [view.camera for view in load_run_scene(RunDir(run), None).train]
    return {
        share: mesh_from_asset(
            asset, cameras, ExportConfig(faces=1000, texture_size=64, grid=32, asset_normals=share, frame="dataset")
        )
        for share in (0.0, 0.5, 1.0)
    }


def test_the_export_mixes_the_gaussians_normals_at_the_share_it_is_given(disk_meshes):
    positions = disk_meshes[0.0].positions
    for mesh in disk_meshes.values():  # the share moves only the normals
        assert np.array_equal(mesh.positions, positions) and np.array_equal(mesh.faces, disk_meshes[0.0].faces)
    radial = unit(positions)  # the sphere's true normals
    errors = {share: angle_degrees(mesh.normals, radial).mean() for share, mesh in disk_meshes.items()}
    # the disks lie tangent to the sphere, so their normals are the true ones; the coarse surface's are not
    assert errors[1.0] < 0.6 * errors[0.0] and errors[0.5] < errors[0.0]
    assert angle_degrees(disk_meshes[0.0].normals, disk_meshes[1.0].normals).mean() > 1.0
    halfway = unit(disk_meshes[0.0].normals + disk_meshes[1.0].normals)
    assert np.allclose(disk_meshes[0.5].normals, halfway, atol=1e-9)


def test_unit_normals_replaces_zero_length_normals():
    from matspray.export.normals import unit_normals

    positions = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]])
    normals = np.array([[2.0, 0, 0], [0, 0, 0], [0, 1e-9, 0], [np.nan, 0, 0]])
    out = unit_normals(normals, positions)
    assert np.allclose(np.linalg.norm(out, axis=-1), 1.0)
    assert (
        np.allclose(out[0], [1, 0, 0])
        and np.allclose(out[1], [-1, 0, 0])
        and np.allclose(out[2], [0, 1, 0])
        and np.allclose(out[3], [0, -1, 0])
    )


def noisy_sphere(subdivisions: int = 5, noise: float = 0.01, seed: int = 0):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    vertices = sphere.vertices * (1.0 + noise * rng.standard_normal(len(sphere.vertices)))[:, None]
    return trimesh.Trimesh(vertices, sphere.faces, process=False)


def test_smoothed_normals_of_a_noisy_sphere_are_closer_to_the_analytic_ones_and_positions_stay():
    from matspray.export.normals import angle_degrees, smoothed_vertex_normals

    mesh = noisy_sphere()
    before = np.asarray(mesh.vertices).copy()
    analytic = before / np.linalg.norm(before, axis=-1, keepdims=True)
    raw = angle_degrees(smoothed_vertex_normals(mesh, 0), analytic)
    smooth = angle_degrees(smoothed_vertex_normals(mesh, 10), analytic)  # the export's default
    smoother = angle_degrees(smoothed_vertex_normals(mesh, 40), analytic)
    assert np.allclose(smoothed_vertex_normals(mesh, 0), mesh.vertex_normals)  # 0 passes: the surface's own normals
    assert smooth.mean() < 0.6 * raw.mean() and np.percentile(smooth, 90) < 0.6 * np.percentile(raw, 90)
    assert smoother.mean() < 0.35 * raw.mean()
    assert np.array_equal(np.asarray(mesh.vertices), before)  # only a copy is smoothed
    # a surface without noise keeps its normals: smoothing moves them by less than half a degree
    exact = noisy_sphere(noise=0.0)
    directions = np.asarray(exact.vertices) / np.linalg.norm(exact.vertices, axis=-1, keepdims=True)
    assert angle_degrees(smoothed_vertex_normals(exact, 40), directions).max() < 0.5


def test_the_old_normals_flag_still_parses_into_the_share(capsys):
    from matspray.cli import build_parser
    from matspray.cli.export import mesh_config

    def share(*flags):  # as the mesh's config reads it (a flag not given takes the config's default)
        return mesh_config(build_parser().parse_args(["export", "--run", "r", "--out", "o.glb", *flags])).asset_normals

    assert (share(), share("--normals", "mesh"), share("--normals", "asset")) == (ExportConfig().asset_normals, 0, 1)
    assert share("--asset-normals", "0.25") == 0.25
    with pytest.raises(SystemExit):
        share("--normals", "shiny")
    assert "'shiny': choose mesh or asset, or pass --asset-normals SHARE" in capsys.readouterr().err
