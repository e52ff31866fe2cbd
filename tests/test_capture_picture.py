"""`benchmarks.capture_picture`: the README's first picture, a held-out photo beside the asset under its own light
and under others, all cut to one square around the object."""

import pytest
import torch

from benchmarks.capture_picture import WHITE, main, picture
from benchmarks.real_captures import results_name
from matspray.data import load_run_scene
from matspray.data.images import read_image
from matspray.eval.relit_crops import crop, square_box
from matspray.method.relight import render_relit
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir
from tests.scenes import ring_cameras, sky_map, sphere_of_disks, write_disk_sphere_run


@pytest.fixture(scope="module")
def sphere_run(tmp_path_factory):
    """A run of the disk sphere whose asset is the truth and whose estimated light is the sky its photos were made
    under; views 0 and 1 trained on, 2 and 3 held out."""
    return write_disk_sphere_run(
        tmp_path_factory.mktemp("picture"), 300, ring_cameras(4, size=40), slice(0, 2), slice(2, 4)
    )


def test_the_estimated_light_column_is_the_held_out_photo_over_white(sphere_run):
    row, view, labels = picture(RunDir(sphere_run), "r_003", ["studio"], 24)
    assert view == "r_003" and labels == ["photo", "its estimated light", "studio"] and row.shape == (24, 72, 3)
    photo = next(v for v in load_run_scene(RunDir(sphere_run)).test if v.name == "r_003")
    g, normals, materials = sphere_of_disks(300)
    from matspray.method.asset import Asset

    _, alpha = render_relit(
        Asset(g, materials, normals), photo.camera, EnvironmentMap.from_tensor(sky_map()).prefilter()
    )
    box = square_box([alpha])
    torch.testing.assert_close(row[:, :24], crop(photo.image, box, 24))  # the photo, cut to the object's square
    # the asset is the truth and its light the photos' own: inside the object the column is the photo (whose
    # background the dataset keeps as alpha, composited here over white)
    over_white = photo.image * photo.alpha[..., None] + WHITE * (1 - photo.alpha[..., None])
    assert float((row[:, 24:48] - crop(over_white, box, 24)).abs().mean()) < 0.02
    assert float((row[:, 48:] - row[:, 24:48]).abs().mean()) > 0.02  # another light shades it otherwise


def test_the_picture_is_written_and_a_view_that_was_trained_on_is_refused(sphere_run, tmp_path, capsys):
    out = tmp_path / "picture.png"
    main(["--run", str(sphere_run), "--lights", "studio", "sunset", "--size", "16", "--out", str(out)])
    rgb, _ = read_image(out)
    assert tuple(rgb.shape) == (16, 64, 3) and "held-out view r_002" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no held-out view r_000 .*: r_002, r_003"):
        main(["--run", str(sphere_run), "--view", "r_000", "--out", str(out)])


def test_each_preset_keeps_its_own_results_file():
    assert results_name("skull", "demo") == "real-captures-skull.json"  # the tables' file of the demo preset
    assert results_name("skull", "quality") == "real-captures-skull-quality.json"
