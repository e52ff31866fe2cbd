"""The corruptions that fuzzing found unhandled, kept as fixed cases: each is refused by `matspray info` with
exit status 2 and one stderr line naming the file (and the frame and field), never a traceback or a run
that trains on it. The generated cases are in tests/test_fuzz_*.py."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from matspray.cli import main
from matspray.data import load_scene, write_image
from matspray.data.images import write_raw
from matspray.errors import DataError
from matspray.geometry.ply import read_ply, write_ply
from tests.test_captures import one_frame
from tests.test_ply import random_gaussians
from tests.test_readers import C2W_GL, FOCAL, H, W, blender_folder, write_colmap


def refusal(data: Path) -> str:
    """The one line `matspray info data` prints when it refuses the dataset (exit status 2). The command's own
    `main` runs in this process: the same code as `python -m matspray`, without a fresh interpreter's 3 s of imports
    per case; an exception it let through (a traceback for a user) fails the test."""
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
        status = main(["info", str(data)])
    assert status == 2, stderr.getvalue()
    lines = stderr.getvalue().strip().splitlines()
    assert len(lines) == 1, stderr.getvalue()
    return lines[0]


def edit_frame(json_path: Path, index: int, **fields) -> None:
    meta = json.loads(json_path.read_text())
    meta["frames"][index].update(fields)
    json_path.write_text(json.dumps(meta))


def test_zero_transform_matrix(tmp_path):
    blender_folder(tmp_path)
    edit_frame(tmp_path / "transforms_train.json", 1, transform_matrix=np.zeros((4, 4)).tolist())
    line = refusal(tmp_path)
    assert "transforms_train.json: frame 1 ('train/r_001'): 'transform_matrix' is not a rigid camera pose" in line
    assert "last row" in line


def test_rotation_scaled_by_five(tmp_path):
    pose = np.array(C2W_GL, dtype=float)
    pose[:3, :3] *= 5.0
    blender_folder(tmp_path)
    edit_frame(tmp_path / "transforms_train.json", 0, transform_matrix=pose.tolist())
    line = refusal(tmp_path)
    assert "frame 0 ('train/r_000'): 'transform_matrix' is not a rigid camera pose: its rotation part is scaled" in line
    assert "column lengths 5, 5, 5" in line


def test_focal_length_as_a_word(tmp_path):
    one_frame(tmp_path, frame_extra={"fl_x": "fifty"})
    line = refusal(tmp_path)
    assert "transforms.json: frame 0 ('images/a.png'): 'fl_x' must be a number > 0, got \"fifty\"" in line


@pytest.mark.parametrize("focal", [0.0, -30.0])
def test_zero_or_negative_focal_length(tmp_path, focal):
    one_frame(tmp_path, meta_extra={"fl_x": focal})
    line = refusal(tmp_path)
    assert f"transforms.json: top-level 'fl_x' must be a number > 0, got {json.dumps(focal)}" in line


@pytest.mark.parametrize("angle", [0.0, -0.8])
def test_zero_or_negative_field_of_view(tmp_path, angle):
    blender_folder(tmp_path, meta_extra={"camera_angle_x": angle})
    line = refusal(tmp_path)
    assert "transforms_train.json: top-level 'camera_angle_x' must be an angle in radians between 0 and pi" in line


@pytest.mark.parametrize("bare", ["grey16", "rgb"])
def test_one_view_without_alpha_among_views_with_alpha(tmp_path, bare):
    blender_folder(tmp_path, frames=[{"file_path": f"train/r_00{i}", "transform_matrix": C2W_GL} for i in range(3)])
    image = tmp_path / "train" / "r_001.png"
    if bare == "grey16":
        write_raw(image, torch.rand(H, W), bits=16)
    else:
        write_image(image, torch.rand(H, W, 3))
    line = refusal(tmp_path)
    assert (
        f"{image}: has no alpha channel or mask, but 2 of the 3 views in the train split have one (1 have none)" in line
    )


def test_focal_length_as_a_numeric_string_is_read_as_the_number(tmp_path):
    """Repaired, not refused: nerfstudio's own float() reads "50.0", so exporters that write it work there."""
    blender_folder(tmp_path, meta_extra={"fl_x": str(FOCAL), "w": W, "h": H})
    scene = load_scene(tmp_path)
    assert float(scene.train[0].camera.K[0, 0]) == pytest.approx(FOCAL)


@pytest.mark.parametrize(
    "name, edit, problem",
    [
        (
            "points3D.bin",
            lambda blob: blob[:-4],
            "ends inside the number of track entries of point 1",
        ),  # pycolmap hung on it
        ("cameras.bin", lambda blob: (1 << 40).to_bytes(8, "little") + blob[8:], "says it holds 1099511627776 cameras"),
        (
            "cameras.bin",
            lambda blob: blob[:12] + (99).to_bytes(4, "little") + blob[16:],
            "camera 1 has the unknown camera model id 99",
        ),
    ],
)
def test_damaged_colmap_binary_model(tmp_path, name, edit, problem):
    """pycolmap hangs or crashes on a truncated .bin file or a count past its end: refused before it reads them."""
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, n_images=2)
    path = tmp_path / "sparse" / "0" / name
    path.write_bytes(edit(path.read_bytes()))
    line = refusal(tmp_path)
    assert f"{path}: is not a valid COLMAP binary model: {problem}" in line


def test_zero_quaternion_in_a_ply(tmp_path):
    """A Gaussian with rot_0..3 all 0 has no rotation (3DGS divides by its length): refused, naming the row."""
    gaussians = random_gaussians(5, 1)
    gaussians.quats[3] = 0.0
    write_ply(tmp_path / "g.ply", gaussians)
    with pytest.raises(
        DataError, match=r"g\.ply: vertex row 3 has a zero quaternion \(rot_0\.\.3 all 0\).*set rot_0\.\.3 to 1 0 0 0"
    ):
        read_ply(tmp_path / "g.ply")


# ---------------------------------------------------------------------------------------- glTF (tests/test_fuzz_glb.py)
def glb_with(tmp_path: Path, edit) -> Path:
    """The fuzzed two-mesh textured .glb of tests/test_fuzz_glb.py with its JSON document edited by `edit`."""
    pytest.importorskip("pygltflib")
    from matspray.gltf import write_glb
    from tests.test_fuzz_glb import EXTRAS, MATERIALS, PRIMITIVES, pack, split

    write_glb(tmp_path / "intact.glb", PRIMITIVES, MATERIALS, extras=EXTRAS)
    document, binary = split((tmp_path / "intact.glb").read_bytes())
    edit(document)
    path = tmp_path / "edited.glb"
    path.write_bytes(pack(document, binary))
    return path


def one_line(error) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize(
    "edit, problem",
    [
        # IndexError, TypeError and AttributeError deep in the reader before
        (
            lambda d: d["meshes"][0]["primitives"][0].update(indices=99),
            "meshes[0].primitives[0].indices refers to accessors[99], but the file has 6",
        ),
        (
            lambda d: d["accessors"][0].update(bufferView=None, count=None),
            "accessors[0].count must be a whole number >= 0, got null",
        ),
        (lambda d: d.update(asset=5), "not a glTF 2.0 document"),
        # accepted before: a NaN colour, a POSITION of the wrong type, float indices truncated to integers
        (
            lambda d: d["materials"][1]["pbrMetallicRoughness"].update(baseColorFactor=[float("nan"), 0, 0, 1]),
            "materials[1].pbrMetallicRoughness.baseColorFactor must be a list of 4 finite numbers, got [NaN, 0, 0, 1]",
        ),
        (
            lambda d: d["accessors"][0].update(type="SCALAR", count=12),
            "accessor 0 (SCALAR of component type 5126) cannot be the POSITION of mesh 'quad'",
        ),
        (
            lambda d: d["accessors"][3].update(componentType=5126),
            "accessor 3 (SCALAR of component type 5126) cannot be the indices of mesh 'quad'",
        ),
    ],
)
def test_glb_document_with_a_wrong_field(tmp_path, edit, problem):
    from matspray.gltf import read_gltf

    path = glb_with(tmp_path, edit)
    with pytest.raises(DataError) as error:
        read_gltf(path)
    assert one_line(error).startswith(f"{path}: {problem}"), str(error.value)


def test_glb_texture_transform_scaled_past_any_texel(tmp_path):
    """KHR_texture_transform scale 1e300: a RuntimeError in torch.arange when synth laid the texture out before."""
    from matspray.gltf import read_gltf
    from matspray.synth.gltf_object import asset_parts

    path = glb_with(
        tmp_path,
        lambda d: d["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].update(
            extensions={"KHR_texture_transform": {"scale": [1e300, 1.0]}}
        ),
    )
    with pytest.raises(DataError) as error:
        asset_parts(read_gltf(path), "fit")
    assert (
        "mesh 'quad': its texture coordinates, with the texture's KHR_texture_transform, reach texel 6e+300"
        in one_line(error)
    )


def test_glb_null_texture_transform_field_is_its_default(tmp_path):
    """ "rotation": null was a TypeError; null is the schema's default, as for every other field."""
    from matspray.gltf import read_gltf

    path = glb_with(
        tmp_path,
        lambda d: d["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"].update(
            extensions={"KHR_texture_transform": {"rotation": None, "scale": [2.0, 2.0]}}
        ),
    )
    transform = read_gltf(path).materials[0].base_color_texture.transform
    assert transform.rotation == 0.0 and transform.scale == (2.0, 2.0)


def test_glb_node_flattened_by_a_zero_scale_keeps_its_normals(tmp_path):
    """A node scaled by 0 along the quad's normal: np.linalg.inv raised LinAlgError on the singular transform."""
    from matspray.gltf import read_gltf

    path = glb_with(tmp_path, lambda d: d["nodes"][0].update(scale=[1.0, 1.0, 0.0]))
    np.testing.assert_allclose(read_gltf(path).primitives[0].normals, np.tile([0.0, 0.0, 1.0], (4, 1)))


def test_exported_glb_with_a_bad_frame_in_its_extras(tmp_path):
    """eval --glb: a ConfigError that named no file before."""
    from matspray.eval.glb import read_glb_parts

    path = glb_with(tmp_path, lambda d: d["asset"]["extras"]["matspray"].update(frame=5))
    with pytest.raises(DataError) as error:
        read_glb_parts(path)
    assert (
        one_line(error)
        == f"{path}: asset.extras.matspray.frame is 5, not gltf or dataset (pass --frame gltf or --frame dataset)"
    )


# --------------------------------------------------------------------- photo folders (tests/test_fuzz_photo_folders.py)
def prepared(tmp_path: Path, name: str):
    from PIL import Image

    from matspray.data.sfm import prepare_photo

    out = tmp_path / "prepared"
    out.mkdir(exist_ok=True)
    size = prepare_photo(tmp_path / name, out, 1600, None, None)
    with Image.open(out / name) as image:
        return size, image.format, np.asarray(image.convert("L"), dtype=np.float64)


def test_16_bit_grey_photo_is_scaled_not_clipped(tmp_path):
    """PIL's convert("RGB") clips 16-bit grey at 255: the photo came out white."""
    from PIL import Image

    Image.fromarray(np.full((40, 50), 20000, dtype=np.uint16)).save(tmp_path / "grey16.png")
    size, _, values = prepared(tmp_path, "grey16.png")
    assert size == (50, 40) and abs(values.mean() - 20000 / 257) < 1


def test_photo_in_another_format_behind_a_jpg_suffix_is_written_as_jpeg(tmp_path):
    """A TIFF named .jpg was copied as it was, for pycolmap to read as a JPEG."""
    from PIL import Image

    Image.new("RGB", (40, 40), (90, 120, 150)).save(tmp_path / "tiff.jpg", format="TIFF")
    assert prepared(tmp_path, "tiff.jpg")[1] == "JPEG"


def test_tiny_photo_is_refused_before_structure_from_motion(tmp_path):
    """A 2x2 photo went to SfM, which ran and then said 'only 0 of 3 photos could be registered'."""
    from PIL import Image

    Image.new("RGB", (2, 2)).save(tmp_path / "tiny.png")
    with pytest.raises(DataError) as error:
        prepared(tmp_path, "tiny.png")
    assert one_line(error).startswith(
        f"{tmp_path / 'tiny.png'}: is 2x2 pixels; structure from motion needs photos of at least 24 pixels a side"
    )


# ----------------------------------------------------------------------- run folders (tests/test_fuzz_run_artifacts.py)
def run_folder(tmp_path: Path) -> Path:
    """A run folder's bare bones: dataset.json, one finished stage (asset)."""
    from matspray.rundir import RunDir

    (tmp_path / "dataset.json").write_text(json.dumps({"source": "/data", "train_views": ["a"], "test_views": []}))
    RunDir(tmp_path).finish_stage("asset", "f1", {}, 1.0)
    return tmp_path


@pytest.mark.parametrize("record", [b"[]", b"\xff\x00garbage"])  # AttributeError and UnicodeDecodeError before
def test_damaged_stage_record_means_the_stage_is_made_again(tmp_path, record):
    from matspray.rundir import RunDir

    run = run_folder(tmp_path)
    (run / "asset" / "stage.json").write_bytes(record)
    assert RunDir(run).stage_done("asset", "f1", []) is False


def test_damaged_timings_are_replaced_when_a_stage_finishes_and_named_when_read(tmp_path):
    """A cut timings.json made every finishing stage fail with a JSONDecodeError; a word for seconds broke `run`'s
    summary line."""
    from matspray.rundir import RunDir

    run = run_folder(tmp_path)
    (run / "timings.json").write_text('{"geometry": 1.')
    RunDir(run).record_timing("lift", 2.0)
    assert RunDir(run).timings() == {"lift": 2.0}
    (run / "timings.json").write_text('{"geometry": "slow"}')
    with pytest.raises(DataError) as error:
        RunDir(run).timings()
    assert one_line(error).startswith(f'{run / "timings.json"}: geometry: "slow" is not a number of seconds (delete it')


def test_damaged_dataset_record(tmp_path):
    """`[]` was an AttributeError in claim (matspray run); a cut file a JSONDecodeError in eval, relight and view."""
    from matspray.rundir import RunDir

    run = run_folder(tmp_path)
    (run / "dataset.json").write_text("[]")
    with pytest.raises(DataError) as error:
        RunDir(run).claim({"source": "/data"})
    assert (
        "dataset.json: holds a list, not the dataset record `matspray run` writes (delete it, or allow overwriting"
        in one_line(error)
    )
    (run / "dataset.json").write_text("{")
    with pytest.raises(DataError) as error:
        RunDir(run).dataset()
    assert "dataset.json: is not readable JSON" in one_line(error) and "--overwrite" in str(error.value)


def test_damaged_lift_result(tmp_path):
    """A cut projected.pt was a RuntimeError from torch.load; values of fewer Gaussians than it keeps were trusted."""
    from matspray.method.lift import LiftResult, load_lift, save_lift

    path = tmp_path / "projected.pt"
    save_lift(
        LiftResult(
            torch.rand(2, 1, 5), torch.ones(2, 1, dtype=torch.bool), torch.tensor([True, True, False]), ["a"], {}
        ),
        path,
    )
    assert load_lift(path, "cpu").values.shape == (2, 1, 5)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(DataError) as error:
        load_lift(path, "cpu")
    assert (
        one_line(error)
        == f"{path}: is not a readable lift result (RuntimeError) (delete it and rerun `matspray run` to lift again)"
    )
    save_lift(
        LiftResult(torch.rand(2, 1, 5), torch.ones(2, 1, dtype=torch.bool), torch.tensor([True, False]), ["a"], {}),
        path,
    )
    with pytest.raises(DataError, match=r"its values are not \[1, 1, 5\]"):
        load_lift(path, "cpu")


def test_damaged_masks_stage(tmp_path):
    """region.json with a word for the radius broke describe() (ValueError); cut files were JSON or torch tracebacks."""
    from matspray.geometry.region import ObjectRegion
    from matspray.method.masks import ObjectMasks, read_object_masks, read_region, write_object_masks

    folder = tmp_path / "masks"
    write_object_masks(
        folder,
        ObjectMasks(
            ObjectRegion((0.0, 0.0, 0.0), 1.0),
            torch.ones(3, dtype=torch.bool),
            {"train": {"a": torch.rand(4, 4)}, "test": {}},
        ),
    )
    assert len(read_object_masks(folder).inside) == 3
    (folder / "region.json").write_text('{"center": [0, 0, 0], "radius": "big"}')
    with pytest.raises(DataError) as error:
        read_region(folder)
    assert one_line(error).startswith(
        f"{folder / 'region.json'}: does not describe an object region"
    ) and f"delete {folder}" in str(error.value)
    (folder / "masks.pt").write_bytes((folder / "masks.pt").read_bytes()[:200])
    with pytest.raises(DataError) as error:
        read_object_masks(folder)
    assert one_line(error).startswith(f"{folder / 'masks.pt'}: is not a readable masks file")


def test_damaged_asset_side_files(tmp_path):
    """visibility.pt holding no tensor (AttributeError), a cut history.json (JSONDecodeError in eval's report), a
    predictor.json holding a list (AttributeError in `matspray predict`)."""
    from matspray.method.asset import read_history, read_visibility
    from matspray.predictors import read_predictor_info

    torch.save({"format": "matspray-visibility-1", "values": {"a": 1}}, tmp_path / "visibility.pt")
    with pytest.raises(DataError, match=r"visibility.pt: holds a dict as its values, not a tensor \(delete it"):
        read_visibility(tmp_path / "visibility.pt", 3)
    (tmp_path / "history.json").write_text('[{"step": ')
    with pytest.raises(
        DataError, match=r"history.json: is not readable JSON .*\(delete it: it only holds the loss curves"
    ):
        read_history(tmp_path)
    (tmp_path / "materials2d").mkdir()
    (tmp_path / "materials2d" / "predictor.json").write_text("[]")
    with pytest.raises(DataError, match=r"predictor.json: holds a list, not the record `matspray predict` writes"):
        read_predictor_info(tmp_path)


def test_damaged_file_of_a_finished_stage_says_which_folder_to_delete(tmp_path):
    """A cut geometry/gaussians.ply was named, but with nothing to do about it."""
    from matspray.rundir import RunDir

    run = run_folder(tmp_path)
    write_ply(run / "geometry" / "gaussians.ply", random_gaussians(3, 1))
    RunDir(run).finish_stage("geometry", "f2", {}, 1.0)
    path = run / "geometry" / "gaussians.ply"
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(DataError) as error:
        read_ply(path)
    assert one_line(error).endswith(
        f"(delete {run / 'geometry'} and rerun `matspray run` with the same settings to make it again)"
    )
