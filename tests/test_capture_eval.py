"""A run on a capture without ground truth: `matspray eval` scores its held-out photos and writes a report
made for it."""

import json
import math
import os

import numpy as np
import pytest
import torch

from matspray.cli import main
from matspray.errors import DataError
from tests.conftest import make_tiny_object
from tests.scenes import capture_like


@pytest.fixture(scope="module")
def capture_run(tmp_path_factory):
    """An unmasked synthetic capture stripped of everything but its photos and cameras (as a real capture is),
    run end to end with the default predictor (none: no-prior) at the test preset."""
    pytest.importorskip("mitsuba")
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    root = tmp_path_factory.mktemp("capture")
    made = make_tiny_object(root / "made", seed=3, train_views=7, background="env", ground=True)
    data = capture_like(made, root / "data")
    run = root / "run"
    config = build_config("test", predictor="auto", **{"refine.iterations": 4})
    Pipeline(data, run, config, progress=False, log=lambda _: None).run_all(("no-prior",))
    return data, run


def test_eval_of_a_capture_scores_held_out_photos_inside_the_mask_and_writes_its_report(capture_run, capsys):
    data, run = capture_run
    code = main(["eval", "--run", str(run), "--credit", "test photos by nobody (CC0)", "--relight", "studio", "sunset"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "no ground-truth materials" in printed and "held-out PSNR" in printed
    metrics = json.loads((run / "eval" / "heldout.json").read_text())
    held = metrics["heldout"]
    assert held["views"] == 2 and [r["view"] for r in held["per_view"]] == ["r_000", "r_001"]
    assert set(held["summary"]) == {"radiance", "no-prior"}
    assert 0.0 < held["mask_coverage"]["min"] <= held["mask_coverage"]["max"] < 1.0
    for key in ("radiance", "no-prior"):
        assert math.isfinite(held["summary"][key]["psnr"]) and 0.0 < held["summary"][key]["ssim"] <= 1.0
    assert metrics["train"]["views"] >= 1
    page = (run / "report.html").read_text()
    assert "test photos by nobody (CC0)" in page and "Held-out photos" in page and "Relit under other lights" in page
    assert "Object region" in page and "Estimated light" in page
    # the sharpness figure: LPIPS inside the mask (the tests have its weights) and the gradient energy share
    assert "<h2>Sharpness</h2>" in page and (run / "report" / "sharpness_r_000.png").exists()
    for key in ("radiance", "no-prior"):
        share = held["summary"][key]["gradient_share"]
        assert 0.0 < share < 2.0 and f"| {share:.2g} |" in printed  # the table `eval` prints
        assert f"<td>{share:.2g}</td>" in page
    assert all(path not in page for path in ("/tmp", "/root", "/home", str(run), str(data)))
    for name in (
        "photo_r_000",
        "render_r_000_radiance",
        "render_r_000_no-prior",
        "relit_r_000_no-prior_studio",
        "envmap_no-prior",
    ):
        assert (run / "report" / f"{name}.png").exists(), name


def test_held_out_score_is_the_masked_metric_of_the_render_against_the_photo(capture_run):
    from matspray.data import load_scene
    from matspray.eval.evaluate import evaluate_images
    from matspray.eval.heldout import photo_renders, score_photos
    from matspray.rundir import RunDir

    data, run = capture_run
    scene = load_scene(data)
    rendered = photo_renders(RunDir(run), scene.test, "test", progress=False)
    scored = score_photos(rendered, lpips=None)
    first = rendered[0]
    direct = evaluate_images(first.renders["radiance"], first.view.image, first.mask, None)
    assert scored["per_view"][0]["radiance"]["psnr"] == pytest.approx(direct["psnr"])
    assert scored["per_view"][0]["mask_coverage"] == pytest.approx(float(first.mask.mean()))
    # the gradient energy share: the render's (sRGB-encoded, as the metrics compare) over the photo's, in the mask
    from matspray.data.images import linear_to_srgb
    from matspray.metrics import gradient_energy

    def energy(rgb):
        return gradient_energy(linear_to_srgb(rgb.clamp(0, 1)), first.mask)

    share = energy(first.renders["radiance"]) / energy(first.view.image)
    assert scored["per_view"][0]["radiance"]["gradient_share"] == pytest.approx(share)
    # the geometry reproduces the held-out photo far better than a black picture would
    black = evaluate_images(torch.zeros_like(first.view.image), first.view.image, first.mask, None)
    assert direct["psnr"] > black["psnr"] + 3.0


def test_an_empty_object_mask_is_refused_not_scored(capture_run):
    from matspray.data import load_scene
    from matspray.eval.heldout import photo_renders, score_photos
    from matspray.rundir import RunDir

    data, run = capture_run
    rendered = photo_renders(RunDir(run), load_scene(data).test[:1], "test", progress=False)
    rendered[0].mask = torch.zeros_like(rendered[0].mask)
    with pytest.raises(DataError, match="r_000: its object mask is empty"):
        score_photos(rendered, lpips=None)


def test_report_shows_other_runs_of_the_capture_cropped_beside_it(capture_run, tmp_path, capsys):
    import shutil

    from PIL import Image

    data, run = capture_run
    before = tmp_path / "before"
    shutil.copytree(run, before)
    code = main(["eval", "--run", str(run), "--no-report"])  # scores only
    assert code == 0 and not (run / "report" / "compare_r_000_studio.png").exists()
    code = main(["eval", "--run", str(run), "--env", "studio", "--compare", str(before)])
    assert code == 0, capsys.readouterr().err
    page = (run / "report.html").read_text()
    assert "Beside other runs of this capture" in page and str(before) not in page  # no path of the machine:
    assert f"{os.path.relpath(before, run)} (relative to this run's folder)" in page  # the other run, from this one
    for name in ("r_000", "r_001"):
        with Image.open(run / "report" / f"compare_{name}_studio.png") as picture:
            assert picture.size == (3 * 256, 256)  # photo, this run, the other run
            pixels = torch.from_numpy(np.array(picture.convert("RGB"))).reshape(256, 3, 256, 3)
        # the same asset in both runs: the same crop
        assert torch.equal(pixels[:, 1], pixels[:, 2])


def test_compare_with_a_run_of_another_capture_is_refused_before_any_work(capture_run, tmp_path, capsys):
    import shutil

    data, run = capture_run
    other = tmp_path / "other"
    shutil.copytree(run, other)
    record = json.loads((other / "dataset.json").read_text())
    record["source"] = str(tmp_path / "elsewhere")
    (other / "dataset.json").write_text(json.dumps(record))
    held = run / "eval" / "heldout.json"
    stamp = held.stat().st_mtime_ns if held.exists() else None
    assert main(["eval", "--run", str(run), "--compare", str(other)]) == 2
    err = capsys.readouterr().err
    assert f"{other} was made from {tmp_path / 'elsewhere'}" in err and "compare runs of the same capture" in err
    assert (held.stat().st_mtime_ns if held.exists() else None) == stamp  # nothing scored or written


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--aligned"], "--aligned is for datasets with ground truth (a capture's photos need no alignment)"),
        (["--env", "nosuch"], "unknown environment map 'nosuch'"),
        (["--no-report", "--env", "studio"], "--env is for a capture's report, which --no-report leaves out"),
    ],
)
def test_flags_a_capture_would_not_read_are_refused_before_any_work(capture_run, capsys, flags, message):
    """Each was ignored before (or, a bad light, failed after the held-out views were scored)."""
    data, run = capture_run
    held = run / "eval" / "heldout.json"
    stamp = held.stat().st_mtime_ns if held.exists() else None
    assert main(["eval", "--run", str(run), *flags]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert (held.stat().st_mtime_ns if held.exists() else None) == stamp


def test_flags_of_the_other_kind_of_evaluation_are_refused(tmp_path, capsys):
    assert main(["eval", "--run", str(tmp_path), "--spp", "4", "--frame", "gltf"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "matspray eval: error: --frame and --spp are for --glb (the evaluation of an exported mesh)"
    assert main(["eval", "--glb", str(tmp_path / "mesh.glb"), "--credit", "photos by me"]) == 2
    assert capsys.readouterr().err.strip() == "matspray eval: error: --credit is for --run, not --glb"


def test_a_flash_the_asset_learned_lights_its_held_out_photos_and_the_report_names_it(capture_run, tmp_path, capsys):
    import shutil

    from matspray.data import load_scene
    from matspray.eval.heldout import photo_renders
    from matspray.method.refine.camera_light import CAMERA_LIGHT_FILE, CameraLight
    from matspray.presets import asset_stage
    from matspray.rundir import RunDir

    data, run = capture_run
    flashed = tmp_path / "flashed"
    shutil.copytree(run, flashed)
    views = load_scene(data).test[:1]

    def render():
        return photo_renders(RunDir(flashed), views, "test", progress=False)[0]

    before = render()
    path = flashed / asset_stage("no-prior") / CAMERA_LIGHT_FILE
    CameraLight(torch.tensor([0.5, 0.5, 0.5]), 2.0, "on").save(path)
    after = render()
    inside = after.mask > 0.5
    assert torch.equal(after.renders["radiance"], before.renders["radiance"])  # the geometry's colours: no flash
    added = (after.renders["no-prior"] - before.renders["no-prior"])[inside]
    assert float(added.min()) >= -1e-5 and float(added.mean()) > 0.01
    CameraLight(torch.tensor([0.5, 0.5, 0.5]), 2.0, "auto").save(path)  # the renders' PNGs say no flash fired
    assert torch.equal(render().renders["no-prior"], before.renders["no-prior"])
    code = main(["eval", "--run", str(flashed), "--env", "studio"])
    assert code == 0, capsys.readouterr().err
    assert (
        "with a flash at the camera on the flash photos (RGB 0.50, 0.50, 0.50)" in (flashed / "report.html").read_text()
    )
