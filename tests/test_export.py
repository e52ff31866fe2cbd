"""`matspray export`: a run's asset as a textured glTF 2.0 mesh (surface, decimation, atlas, baking, frames)."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import torch

if TYPE_CHECKING:
    import trimesh

pytest.importorskip("trimesh")
pytest.importorskip("xatlas")
pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")
pytest.importorskip("pygltflib")

from matspray.cli import main  # noqa: E402
from matspray.data import Camera  # noqa: E402
from matspray.data.images import srgb_to_linear  # noqa: E402
from matspray.export.bake import fill_empty, gaussian_weights, rasterize_uv  # noqa: E402
from matspray.export.decimate import decimate  # noqa: E402
from matspray.export.frames import GLTF_FROM_DATASET, dataset_from_file, transform_points  # noqa: E402
from matspray.export.surface import fuse_surface  # noqa: E402
from matspray.gltf.read import read_gltf  # noqa: E402
from tests.conftest import make_tiny_object  # noqa: E402
from tests.scenes import sphere_cameras, sphere_of_disks, write_disk_sphere_run  # noqa: E402

SMALL = ["--faces", "3000", "--texture-size", "128", "--grid", "48"]
VALIDATOR = Path(sys.prefix) / "node" / "node_modules" / "gltf-validator"  # `make setup` installs it there


def make_disk_run(root: Path) -> Path:
    """A run folder holding the disk sphere's asset (true materials, sky light) and a Blender dataset of
    its renders at 12 cameras around it (all training views, the first two also test views)."""
    return write_disk_sphere_run(root, 1500, sphere_cameras(12, 40), slice(None), slice(0, 2))


@pytest.fixture(scope="module")
def disk_run(tmp_path_factory):
    return make_disk_run(tmp_path_factory.mktemp("disks"))


@pytest.fixture(scope="module")
def exported(disk_run, tmp_path_factory):
    """The disk run exported in both frames: {frame: path}."""
    out = tmp_path_factory.mktemp("export")
    paths = {}
    for frame in ("gltf", "dataset"):
        paths[frame] = out / f"disks_{frame}.glb"
        assert main(["export", "--run", str(disk_run), "--out", str(paths[frame]), "--frame", frame, *SMALL]) == 0
    return paths


def test_glb_box_is_in_the_dataset_world_whatever_the_files_frame(exported):
    from matspray.export.frames import glb_box

    y_up, z_up = glb_box(exported["gltf"]), glb_box(exported["dataset"])
    assert np.allclose(y_up, z_up, atol=1e-5)  # both files hold the same mesh, each in its own frame
    low, high = np.asarray(z_up)
    assert (
        (low > -1.4).all() and (high < 1.4).all() and (high - low > 1.8).all()
    )  # the disk sphere around the unit sphere


def test_export_opens_in_trimesh_and_pygltflib_with_its_textures(exported):
    import pygltflib
    import trimesh

    path = exported["gltf"]
    gltf = pygltflib.GLTF2().load(str(path))
    assert len(gltf.meshes) == 1 and len(gltf.materials) == 1
    pbr = gltf.materials[0].pbrMetallicRoughness
    assert pbr.baseColorTexture is not None and pbr.metallicRoughnessTexture is not None
    assert len(gltf.images) == 2 and all(image.mimeType == "image/png" for image in gltf.images)
    attributes = gltf.meshes[0].primitives[0].attributes
    assert attributes.POSITION is not None and attributes.NORMAL is not None and attributes.TEXCOORD_0 is not None
    faces = gltf.accessors[gltf.meshes[0].primitives[0].indices].count // 3
    assert 100 < faces <= 3000

    scene = trimesh.load(str(path))
    (mesh,) = scene.geometry.values()
    assert len(mesh.faces) == faces
    material = mesh.visual.material
    assert material.baseColorTexture.size == (128, 128) and material.metallicRoughnessTexture.size == (128, 128)
    assert (path.parent / "disks_gltf_envmap.exr").exists() and (path.parent / "disks_gltf_envmap.hdr").exists()
    assert not list(path.parent.glob(".*tmp-*")), "a temporary file was left behind"


def test_export_passes_the_khronos_validator(exported):
    if shutil.which("node") is None:
        pytest.skip("node is not installed (the Khronos glTF Validator runs on node)")
    if not VALIDATOR.exists():
        pytest.skip(f"the gltf-validator npm package is not installed at {VALIDATOR} (`make setup` installs it)")
    script = (
        "const v = require(process.argv[1]); const fs = require('fs');"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])))"
        ".then(r => console.log(JSON.stringify(r.issues)), e => { console.error(String(e)); process.exit(1); });"
    )
    for path in exported.values():
        result = subprocess.run(
            ["node", "-e", script, str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120
        )
        assert result.returncode == 0, result.stderr
        issues = json.loads(result.stdout)
        assert issues["numErrors"] == 0, issues["messages"]
        assert issues["numWarnings"] == 0, issues["messages"]


def file_mesh(path: Path):
    asset = read_gltf(path)
    (primitive,) = asset.primitives
    return primitive, asset.materials[0], asset.extras["matspray"]


def test_bounding_box_matches_the_gaussians_in_either_frame_and_the_frames_round_trip(exported, disk_run):
    from matspray.method.asset import read_asset

    means = read_asset(disk_run / "asset").gaussians.means.double().numpy()
    gltf, _, gltf_extras = file_mesh(exported["gltf"])
    data, _, data_extras = file_mesh(exported["dataset"])
    assert gltf_extras["frame"] == "gltf" and data_extras["frame"] == "dataset"
    for positions, matrix in ((gltf.positions, GLTF_FROM_DATASET), (data.positions, np.eye(4))):
        expected = transform_points(matrix, means)
        # the disks (sigma 0.16) reach a little beyond their centres on the unit sphere
        assert np.abs(positions.min(0) - expected.min(0)).max() < 0.2
        assert np.abs(positions.max(0) - expected.max(0)).max() < 0.2
    # the same mesh in both files, mapped onto each other by the stored transforms
    assert gltf.positions.shape == data.positions.shape
    assert np.allclose(transform_points(dataset_from_file(gltf_extras), gltf.positions), data.positions, atol=1e-5)
    assert np.allclose(
        transform_points(np.asarray(gltf_extras["file_from_dataset"]), data.positions), gltf.positions, atol=1e-5
    )
    assert np.allclose(transform_points(dataset_from_file(data_extras), data.positions), data.positions)
    normals_back = gltf.normals @ np.linalg.inv(GLTF_FROM_DATASET[:3, :3]).T
    assert np.allclose(normals_back, data.normals, atol=1e-5)
    # GLTF_FROM_DATASET takes the dataset's up (+Z) to glTF's up (+Y) and is a proper rotation
    assert np.allclose(GLTF_FROM_DATASET[:3, :3] @ [0, 0, 1], [0, 1, 0]) and np.isclose(
        np.linalg.det(GLTF_FROM_DATASET[:3, :3]), 1
    )


def test_baked_texels_hold_the_materials_of_the_gaussians_on_the_surface(exported):
    """The disk sphere's materials are constant over regions (base colour by the sign of x, roughness by
    the sign of y, metallic where z > 0.6): texels well inside a region read back its exact material."""
    primitive, material, extras = file_mesh(exported["dataset"])
    assert extras["bake"] == "gaussians"  # auto, for the full asset
    size = material.base_color_texture.image.shape[0]
    texels = rasterize_uv(primitive.uvs[0], primitive.indices, size)
    points = np.einsum("tk,tkc->tc", texels.bary, primitive.positions[primitive.indices[texels.face]])
    direction = points / np.linalg.norm(points, axis=-1, keepdims=True)
    base = srgb_to_linear(torch.from_numpy(material.base_color_texture.image.reshape(-1, 3)[texels.index])).numpy()
    packed = material.metallic_roughness_texture.image.reshape(-1, 3)[texels.index]
    quantum = 1.5 / 255  # 8-bit textures; the sRGB curve is steepest (x 12.92) only near black
    for mask, expected in ((direction[:, 0] > 0.5, [0.7, 0.25, 0.2]), (direction[:, 0] < -0.5, [0.2, 0.35, 0.7])):
        assert mask.sum() > 100
        assert np.abs(base[mask] - expected).max() < 2 * quantum
    for mask, expected in ((direction[:, 1] > 0.5, 0.3), (direction[:, 1] < -0.5, 0.8)):
        assert np.abs(packed[mask, 1] - expected).max() < quantum
    for mask, expected in ((direction[:, 2] > 0.85, 1.0), (direction[:, 2] < 0.35, 0.0)):
        assert np.abs(packed[mask, 2] - expected).max() < quantum


def test_gaussian_weights_match_a_brute_force_blend():
    gaussians, _, materials = sphere_of_disks(300, seed=3)
    points = np.random.default_rng(0).normal(size=(200, 3))
    points = 1.05 * points / np.linalg.norm(points, axis=-1, keepdims=True)
    min_scale = 0.05
    # brute force: every Gaussian's opacity times its (widened) density, normalised
    cov = gaussians.rotation_matrices().double() * gaussians.scales.double().clamp_min(min_scale)[:, None, :]
    cov = cov @ cov.transpose(1, 2)
    offset = torch.from_numpy(points)[:, None, :] - gaussians.means.double()[None]  # [P, N, 3]
    m2 = torch.einsum("pni,nij,pnj->pn", offset, torch.linalg.inv(cov), offset)
    weights = gaussians.opacities.double()[None] * torch.exp(-0.5 * m2)
    expected = (weights / weights.sum(-1, keepdim=True)) @ materials.double()
    ids, w = gaussian_weights(points, gaussians, len(gaussians), min_scale)
    assert np.allclose(np.einsum("pk,pkc->pc", w, materials.double().numpy()[ids]), expected.numpy(), atol=1e-9)
    ids, w = gaussian_weights(points, gaussians, 16, min_scale)  # the nearest 16 carry nearly all the weight
    assert np.abs(np.einsum("pk,pkc->pc", w, materials.double().numpy()[ids]) - expected.numpy()).max() < 0.05


def test_rasterize_uv_matches_point_in_triangle_brute_force():
    rng = np.random.default_rng(1)
    uvs = rng.uniform(0, 1, size=(30, 2))
    faces = rng.integers(0, 30, size=(12, 3))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    size = 32
    texels = rasterize_uv(uvs, faces, size)
    centres = (np.stack(np.meshgrid(np.arange(size), np.arange(size), indexing="xy"), -1).reshape(-1, 2) + 0.5) / size
    for index, face, bary in zip(texels.index, texels.face, texels.bary):
        assert np.allclose(bary @ uvs[faces[face]], centres[index], atol=1e-9) and (bary >= -1e-9).all()
    covered = np.zeros(size * size, dtype=bool)
    for tri in uvs[faces]:
        edges = [(tri[(i + 1) % 3] - tri[i], centres - tri[i]) for i in range(3)]
        d = np.stack([e[0] * p[:, 1] - e[1] * p[:, 0] for e, p in edges], -1)
        covered |= (d >= -1e-12).all(-1) | (d <= 1e-12).all(-1)
    assert np.array_equal(np.sort(texels.index), np.flatnonzero(covered))
    none = rasterize_uv(uvs, faces[:0], size)  # no triangles: no texels
    assert none.index.shape == none.face.shape == (0,) and none.bary.shape == (0, 3)


def test_fill_empty_takes_the_nearest_filled_texel():
    texture = np.zeros((8, 8, 1))
    filled = np.zeros((8, 8), dtype=bool)
    texture[1, 1], texture[6, 6] = 1.0, 2.0
    filled[1, 1] = filled[6, 6] = True
    out = fill_empty(texture, filled)
    assert out[0, 0, 0] == 1.0 and out[7, 7, 0] == 2.0 and out[2, 1, 0] == 1.0 and out[5, 6, 0] == 2.0
    assert set(np.unique(out)) == {1.0, 2.0}


def test_a_capture_region_bounds_the_surface():
    """A capture's object region (here cut by a plane at z = 0.3, as a table cuts it) bounds the mesh: it closes at
    the cut, with nothing below it, and keeps the part above."""
    from matspray.geometry.region import ObjectRegion

    gaussians, _, _ = sphere_of_disks(1500)
    region = ObjectRegion(center=(0.0, 0.0, 0.0), radius=2.0, plane=(0.0, 0.0, 1.0, -0.3))
    mesh, voxel, _ = fuse_surface(gaussians, sphere_cameras(12, 40), 48, 4.0, 0.5, 0.05, region=region)
    assert mesh.is_watertight and mesh.volume > 0
    z = np.asarray(mesh.vertices)[:, 2]
    assert z.min() > 0.3 - 1.5 * voxel  # nothing below the cut (marching cubes places the cap within a voxel)
    assert z.max() > 1.0  # the top of the sphere is kept
    whole, _, _ = fuse_surface(gaussians, sphere_cameras(12, 40), 48, 4.0, 0.5, 0.05)
    assert np.asarray(whole.vertices)[:, 2].min() < -0.9


def test_surface_is_closed_and_decimation_keeps_the_budget():
    gaussians, _, _ = sphere_of_disks(1500)
    mesh, voxel, _ = fuse_surface(gaussians, sphere_cameras(12, 40), 48, 4.0, 0.5, 0.05)
    assert mesh.is_watertight and mesh.volume > 0  # closed, faces wound outwards
    radius = np.linalg.norm(mesh.vertices, axis=-1)
    assert 0.95 < radius.min() and radius.max() < 1.25  # the disks' surface around the unit sphere
    assert len(mesh.split(only_watertight=False)) == 1
    for budget in (2000, 500):
        small = decimate(mesh, budget)
        assert len(small.faces) <= budget and len(small.faces) > budget * 0.9
        assert np.abs(np.linalg.norm(small.vertices, axis=-1) - 1.1).max() < 0.2


def run_cli(args, capsys):
    code = main(args)
    err = capsys.readouterr().err.strip()
    return code, err


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--variant", "fancy"], "unknown variant 'fancy'"),
        (["--faces", "99"], "face budget must be >= 100"),
        (["--texture-size", "100"], "power of two in [64, 8192]"),
        (["--texture-size", "16384"], "power of two in [64, 8192]"),
        (["--texture-size", "32"], "power of two in [64, 8192]"),
        (["--silhouette-rounds", "-1"], "silhouette fit's rounds must be >= 0"),
        (["--asset-normals", "1.5"], "share of the normals must be in [0, 1], got 1.5"),
        (["--asset-normals", "nan"], "share of the normals must be in [0, 1], got nan"),
        (["--variant", "no-softmax"], "make it with `matspray run --variant no-softmax`"),
    ],
)
def test_bad_settings_are_one_clear_line(disk_run, tmp_path, capsys, extra, message):
    out = tmp_path / "x.glb"
    code, err = run_cli(["export", "--run", str(disk_run), "--out", str(out), *extra], capsys)
    assert code == 2 and message in err and "\n" not in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())


def test_a_run_without_an_asset_and_unwritable_outputs_are_one_clear_line(disk_run, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(disk_run / "dataset.json", bare / "dataset.json")
    code, err = run_cli(["export", "--run", str(bare), "--out", str(tmp_path / "x.glb")], capsys)
    assert code == 2 and "the run has no asset yet (no asset*/asset.ply)" in err and "matspray run --data" in err
    code, err = run_cli(["export", "--run", str(tmp_path), "--out", str(tmp_path / "x.glb")], capsys)
    assert code == 2 and "not a MatSpray run folder" in err
    blocker = tmp_path / "file"
    blocker.write_text("")
    folder = tmp_path / "folder.glb"
    folder.mkdir()
    for out, message in (
        (blocker / "x.glb", f"{blocker} is a file, not a folder"),
        (tmp_path / "x.gltf", "must be a .glb file"),
        (folder, "is a folder"),
    ):
        code, err = run_cli(["export", "--run", str(disk_run), "--out", str(out)], capsys)
        assert code == 2 and message in err and "\n" not in err, err
    for flag, out, message in (  # the splats' file and the page's folder: refused before any work
        ("--splats", blocker / "x.glb", f"{blocker} is a file, not a folder"),
        ("--splats", folder, "is a folder; give a file name ending in .glb or .spz"),
        ("--web", blocker, f"{blocker}: is a file, not a folder"),
        ("--web", blocker / "page", f"{blocker} is a file, not a folder"),
    ):
        code, err = run_cli(
            ["export", "--run", str(disk_run), "--out", str(tmp_path / "m.glb"), flag, str(out)], capsys
        )
        assert code == 2 and message in err and "\n" not in err, err
        assert not (tmp_path / "m.glb").exists()  # the mesh asked for beside them was not made first


def test_a_failed_export_leaves_no_partial_file(disk_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(disk_run, run)
    (run / "asset" / "envmap.exr").write_bytes(b"not an exr")  # fails after the mesh is made, while writing
    out = tmp_path / "out" / "broken.glb"
    code, err = run_cli(["export", "--run", str(run), "--out", str(out), *SMALL], capsys)
    last = err.splitlines()[-1]  # above it: the progress bars
    assert code == 2 and last.startswith("matspray export: error:") and "envmap.exr" in last and "Traceback" not in err
    assert not list(out.parent.iterdir()), list(out.parent.iterdir())


# ------------------------------------------------------------------------------------------ eval --glb
@pytest.fixture(scope="module")
def synth_run(tmp_path_factory):
    """A tiny Mitsuba object (with its true mesh as object.glb) and a short run of the method on it."""
    pytest.importorskip("mitsuba")
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    root = tmp_path_factory.mktemp("synth")
    make_tiny_object(root / "data")
    config = build_config("test", predictor="simulated", **{"refine.iterations": 8})
    Pipeline(root / "data", root / "run", config, progress=False, log=lambda _: None).run_all(["full"])
    return root


def test_eval_glb_of_the_true_object_reproduces_the_truth(synth_run, tmp_path):
    from matspray.eval.glb import evaluate_glb

    metrics = evaluate_glb(
        synth_run / "data" / "object.glb", data=synth_run / "data", out=tmp_path, spp=64, progress=False
    )
    mesh = metrics["mesh"]["summary"]
    assert "gaussians" not in metrics  # the true object was not exported from a run
    assert mesh["basecolor"]["psnr"] > 40 and mesh["roughness"]["psnr"] > 40  # the same ray cast as the truth's maps
    assert (
        mesh["relighting"]["psnr"] > 25
    )  # the same renderer; only Monte Carlo noise differs (26.7 dB: the truth has 4 spp)
    assert (tmp_path / "report.html").exists() and (tmp_path / "metrics.json").exists()


def test_eval_glb_scores_an_export_beside_its_gaussian_asset(synth_run, tmp_path, capsys):
    out = tmp_path / "sphere.glb"
    args = [
        "export",
        "--run",
        str(synth_run / "run"),
        "--out",
        str(out),
        "--frame",
        "dataset",
        "--faces",
        "2000",
        "--texture-size",
        "128",
        "--grid",
        "48",
    ]
    assert main(args) == 0
    assert main(["eval", "--glb", str(out)]) == 0  # the run and the dataset are found through the file's extras
    assert "Gaussians PSNR" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "sphere_eval" / "metrics.json").read_text())
    assert metrics["frame"] == "dataset" and metrics["variant"] == "full"
    mesh, gaussians = metrics["mesh"]["summary"], metrics["gaussians"]["summary"]
    assert mesh["relighting"]["psnr"] > gaussians["relighting"]["psnr"] - 3.0
    page = (tmp_path / "sphere_eval" / "report.html").read_text()
    assert all(f"_{who}.png" in page for who in ("truth", "gaussians", "mesh"))


def test_eval_glb_bad_inputs_are_one_clear_line(tmp_path, capsys):
    code, err = run_cli(["eval", "--glb", str(tmp_path / "missing.glb")], capsys)
    assert code == 2 and "no such file" in err and "matspray export" in err
    code, err = run_cli(["eval"], capsys)
    assert code == 2 and "give --run RUN" in err


def test_the_truth_is_rendered_at_the_datasets_spp_and_a_synth_objects_training_light_is_found(tmp_path):
    import json

    from matspray.errors import DataError
    from matspray.eval.glb import DEFAULT_SPP, dataset_spp
    from matspray.eval.light import training_light_path

    assert dataset_spp(tmp_path) == DEFAULT_SPP and training_light_path(tmp_path) is None  # not a synth object
    (tmp_path / "scene.json").write_text("{not json")
    assert dataset_spp(tmp_path) == DEFAULT_SPP and training_light_path(tmp_path) is None
    (tmp_path / "scene.json").write_text(json.dumps({"settings": {"spp": 7}, "lights": {"train": "sky"}}))
    assert dataset_spp(tmp_path) == 7
    with pytest.raises(DataError, match="training light .sky. named in scene.json is missing"):
        training_light_path(tmp_path)
    (tmp_path / "envmaps").mkdir()
    (tmp_path / "envmaps" / "sky.exr").write_bytes(b"")
    assert training_light_path(tmp_path) == tmp_path / "envmaps" / "sky.exr"


def test_unknown_space_reaching_the_border_is_outside_and_enclosed_unknown_space_inside():
    from matspray.export.surface import open_to_outside

    shape = (9, 9, 9)
    field = torch.ones(shape)
    unknown = torch.zeros(shape, dtype=torch.bool)
    field[2:7, 2:7, 2:7] = -0.5  # an observed shell ...
    field[3:6, 3:6, 3:6] = -1.0  # ... around unknown space
    unknown[3:6, 3:6, 3:6] = True
    field[:, :, 8] = -1.0  # an unknown slab on the border (space no view carved)
    unknown[:, :, 8] = True
    out = open_to_outside(field.reshape(-1), unknown.reshape(-1), shape).reshape(shape)
    assert (out[3:6, 3:6, 3:6] == -1).all() and (out[:, :, 8] == 1).all()
    assert torch.equal(out[~unknown], field[~unknown])


# ------------------------------------------------------------------------------------------ atlas
def torus_surface(grid: int = 96) -> "trimesh.Trimesh":
    """Marching cubes of a torus' signed distance (major 0.65, minor 0.27, the size of a development object):
    the same staircase-noisy normals and tiny faces a fused surface has."""
    import trimesh
    from skimage.measure import marching_cubes

    axis = np.linspace(-1.1, 1.1, grid)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    sdf = np.sqrt((np.sqrt(x**2 + y**2) - 0.65) ** 2 + z**2) - 0.27
    verts, faces, _, _ = marching_cubes(sdf, 0.0, spacing=(axis[1] - axis[0],) * 3)
    return trimesh.Trimesh(verts - 1.1, faces[:, ::-1], process=True)


@pytest.mark.slow
def test_atlas_has_no_zero_area_uv_faces_fills_half_the_texture_and_keeps_the_budget():
    from matspray.export.atlas import atlas_fill, uv_areas, uv_atlas

    surface = torus_surface()
    assert len(surface.faces) > 30_000
    mesh = decimate(surface, 20_000)
    assert 18_000 < len(mesh.faces) <= 20_000
    atlas = uv_atlas(mesh, 1024, 4)  # the export's default texture and gutter
    assert len(atlas.faces) == len(mesh.faces)  # xatlas dropped no face
    assert uv_areas(atlas.uvs, atlas.faces, 1024).min() > 1e-3  # every face owns some texture (main: 644 at UV (0, 0))
    assert atlas_fill(atlas.uvs, atlas.faces, 1024) >= 0.5
    assert atlas.charts < 300  # a few large charts, not one per handful of faces


def test_decimation_drops_duplicate_faces_that_xatlas_would_leave_at_uv_origin():
    import trimesh

    from matspray.export.atlas import uv_areas, uv_atlas

    mesh = trimesh.creation.icosphere(subdivisions=3)
    fin = mesh.faces[0][::-1]  # the same three vertices again, wound the other way
    doubled = trimesh.Trimesh(mesh.vertices, np.vstack([mesh.faces, fin[None]]), process=False)
    clean = decimate(doubled, 10_000)
    assert len(clean.faces) == len(mesh.faces) - 1  # both copies gone
    atlas = uv_atlas(clean, 256, 2)
    assert uv_areas(atlas.uvs, atlas.faces, 256).min() > 1e-3


def test_padding_keeps_charts_apart_at_the_first_mip_level():
    """With the 4-texel gutter split between neighbours by the nearest-texel fill, a 2 x 2 mip texel never
    mixes two charts: level 1 of the mip chain keeps every chart's own colours at its border."""
    from scipy.ndimage import distance_transform_edt
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from matspray.export.atlas import uv_atlas

    size = 256
    atlas = uv_atlas(decimate(torus_surface(64), 6000), size, 4)
    faces, count = atlas.faces, len(atlas.uvs)
    pairs = coo_matrix((np.ones(faces.size), (faces.ravel(), np.roll(faces, 1, axis=1).ravel())), shape=(count, count))
    charts, vertex_chart = connected_components(
        pairs, directed=False
    )  # the atlas is split at seams: components = charts
    assert charts > 1
    texels = rasterize_uv(atlas.uvs, faces, size)
    owner = -np.ones(size * size, dtype=np.int64)
    owner[texels.index] = vertex_chart[faces[texels.face, 0]]
    owner = owner.reshape(size, size)
    filled = owner >= 0
    nearest = distance_transform_edt(~filled, return_distances=False, return_indices=True)
    owner = owner[nearest[0], nearest[1]]  # what `fill_empty` copies into every gutter texel
    blocks = owner.reshape(size // 2, 2, size // 2, 2)
    mixed = (blocks.max((1, 3)) != blocks.min((1, 3))) & filled.reshape(size // 2, 2, size // 2, 2).any((1, 3))
    assert not mixed.any(), f"{int(mixed.sum())} level-1 mip texels mix two charts"


# -------------------------------------------------------------------------------------- surface against wrong depths
def sphere_depths(cameras: list[Camera], radius: float = 1.0) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """What `render_depths` gives for an opaque sphere at the origin: camera z of the first hit (weighted
    by alpha 1) and alpha, 0 where the ray misses."""
    out = []
    for camera in cameras:
        origins, dirs = camera.rays()
        b = (origins * dirs).sum(-1)
        disc = b**2 - ((origins**2).sum(-1) - radius**2)
        hit = disc > 0
        t = -b - disc.clamp_min(0).sqrt()
        z = camera.world_to_camera(origins + t[:, None] * dirs)[:, 2]
        shape = (camera.height, camera.width)
        out.append((torch.where(hit, z, 0.0).reshape(shape).float(), hit.float().reshape(shape)))
    return out


def test_one_view_with_a_wrong_depth_does_not_carve_a_pit():
    """A reflection's Gaussians lie behind the mirror they show: a view whose depth runs deep behind the true
    surface over a patch must not carve the inside that every other view sees as hidden behind the surface."""
    from matspray.export.surface import fuse_tsdf, voxel_grid

    cameras = sphere_cameras(24, 48)
    depths = sphere_depths(cameras)
    depth, alpha = depths[0]
    deep = depth.clone()
    deep[18:30, 18:30] += 0.6  # the patch at the centre of view 0 lies 0.6 behind the true surface
    depths[0] = (deep, alpha)
    centres, voxel, shape = voxel_grid(torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), 40)
    eye = cameras[0].center.float()
    probe = (eye / eye.norm() * 0.6)[None]  # 0.4 under the surface, straight ahead of view 0: inside the pit
    nearest = int(((centres - probe) ** 2).sum(-1).argmin())
    carved, _ = fuse_tsdf(centres, cameras, depths, 4 * voxel, occluded_share=2.0)  # the plain TSDF: one view decides
    field, _ = fuse_tsdf(centres, cameras, depths, 4 * voxel)
    assert carved[nearest] > 0 and field[nearest] < 0
    # the outside is untouched: voxels outside the sphere stay outside, the rest of the inside stays inside
    radius = centres.norm(dim=-1)
    assert (field[radius > 1.0 + 2 * voxel] > 0).all()
    assert (field[radius < 1.0 - 6 * voxel] < 0).all()


def test_depth_trust_is_low_on_smooth_metal_only():
    from matspray.export.surface import depth_trust

    gaussians, _, materials = sphere_of_disks(1500)
    camera = sphere_cameras(1, 40)[0]
    mirror, rough_metal, dielectric = materials.clone(), materials.clone(), materials.clone()
    mirror[:, 3:5] = torch.tensor([0.05, 1.0])  # roughness, metallic
    rough_metal[:, 3:5] = torch.tensor([0.7, 1.0])
    dielectric[:, 3:5] = torch.tensor([0.05, 0.0])
    centre = (slice(15, 25), slice(15, 25))
    assert depth_trust(gaussians, mirror, [camera])[0][centre].max() < 0.05
    assert depth_trust(gaussians, rough_metal, [camera])[0][centre].min() > 0.95
    assert depth_trust(gaussians, dielectric, [camera])[0][centre].min() > 0.95


def test_the_progress_bar_names_every_stage(disk_run, tmp_path, capsys, monkeypatch):
    """Each stage is named when it starts, not at the bar's next refresh: a stage that ends before the bar refreshes
    (the decimation of a small surface) left the next one, 'silhouettes', unnamed. Refreshes held off here as long
    as a run takes make every stage such a stage."""
    import functools

    import matspray.export.export as export

    monkeypatch.setattr(export, "tqdm", functools.partial(export.tqdm, mininterval=1000))
    assert main(["export", "--run", str(disk_run), "--out", str(tmp_path / "x.glb"), *SMALL]) == 0
    bar = [part for part in re.split(r"[\r\n]", capsys.readouterr().err) if part.startswith("export:")]
    for stage in ("surface", "decimate", "silhouettes", "atlas", "bake"):
        assert any(part.rstrip().endswith(f", {stage}]") for part in bar), (stage, bar)
