"""`matspray relight` and `export` without --variant take the asset the run has (full, else photos-only, else the one
it has)."""

import shutil

import pytest

from matspray.cli.relight import relight_run
from matspray.errors import RunError
from matspray.presets import asset_stage
from matspray.rundir import RunDir
from matspray.view.launch import run_variants
from tests.scenes import ring_cameras, write_disk_sphere_run


@pytest.fixture(scope="module")
def no_prior_run(tmp_path_factory):
    """A run whose only asset is no-prior's, as `matspray run --predictor none --variant no-prior` leaves it."""
    root = tmp_path_factory.mktemp("relight")
    run = write_disk_sphere_run(root, 300, ring_cameras(3, size=32), slice(0, 2), slice(2, 3))
    shutil.move(run / asset_stage("full"), run / asset_stage("no-prior"))
    return run


def test_relight_takes_the_runs_only_variant(no_prior_run, tmp_path):
    assert RunDir(no_prior_run).default_variant() == "no-prior"
    written = relight_run(no_prior_run, "forest", "test", tmp_path / "out")
    assert [p.name for p in written] == ["r_002_forest.png"]
    with pytest.raises(RunError, match="no asset for variant 'full'"):  # asked for by name, it is still refused
        relight_run(no_prior_run, "forest", "test", tmp_path / "out", variant="full")


def test_full_is_preferred_then_photos_only_and_a_run_without_assets_is_one_line(no_prior_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(no_prior_run, run)
    # a run without maps that made the user's asset beside the paper's baseline: commands take the user's
    shutil.copytree(run / asset_stage("no-prior"), run / asset_stage("photos-only"))
    assert RunDir(run).default_variant() == "photos-only"
    assert run_variants(run) == ["photos-only", "no-prior"]  # the viewer starts with the first
    shutil.copytree(run / asset_stage("no-prior"), run / asset_stage("full"))
    assert RunDir(run).default_variant() == "full" and run_variants(run) == ["full", "no-prior", "photos-only"]
    for variant in ("full", "no-prior", "photos-only"):
        shutil.rmtree(run / asset_stage(variant))
    with pytest.raises(RunError, match=f"^{run}: the run has no asset yet .*`matspray run --data DATA --out {run}`$"):
        RunDir(run).default_variant()


def test_several_lights_in_one_call(no_prior_run, tmp_path):
    written = relight_run(no_prior_run, ["sky", "city", "sunrise"], "test", tmp_path / "out")
    assert [p.name for p in written] == ["r_002_sky.png", "r_002_city.png", "r_002_sunrise.png"]


def test_a_light_of_negative_radiance_is_refused_in_one_line_naming_the_file(no_prior_run, tmp_path, capsys):
    import torch

    from matspray.cli import main
    from matspray.data.images import write_raw

    light = tmp_path / "negative.exr"
    write_raw(light, torch.full((8, 16, 3), -0.5))
    out = tmp_path / "out"
    assert main(["relight", "--run", str(no_prior_run), "--env", "sky", str(light), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"matspray relight: error: {light}: holds negative radiance (384 values, 100 % of its energy, down to -0.5) "
        "(a light is >= 0 everywhere: re-export the map without negative values)\n"
    )
    assert not out.exists()  # every light is read before anything is written


def test_orbit_flags_for_the_test_views_are_refused(no_prior_run, tmp_path, capsys):
    """--frames and --fps shape the orbit only; with the test views they were ignored without a word."""
    from matspray.cli import main

    out = tmp_path / "out"
    assert main(["relight", "--run", str(no_prior_run), "--env", "sky", "--out", str(out), "--frames", "10"]) == 2
    assert capsys.readouterr().err == "matspray relight: error: --frames is for --views orbit\n"
    assert not out.exists()


def test_resolution_sets_the_frames_long_side_and_the_help_names_the_files_written(no_prior_run, tmp_path, capsys):
    from matspray.cli import main
    from matspray.data.images import read_raw
    from tests.test_newcomer import commands

    help_text = " ".join(commands()["relight"].format_help().split())
    assert "VIEW_LIGHT.png" in help_text and "orbit_LIGHT.mp4" in help_text and "orbit.mp4" not in help_text
    for flag, size in (("--resolution", 64), ("--size", 48)):  # --size: the name people try first
        out = tmp_path / flag
        assert main(["relight", "--run", str(no_prior_run), "--env", "sky", "--out", str(out), flag, str(size)]) == 0
        assert read_raw(out / "r_002_sky.png").shape[:2] == (size, size)  # the dataset's views are 32 x 32
    written = relight_run(no_prior_run, "sky", "orbit", tmp_path / "orbit", frames=2, fps=2, resolution=40)
    names = [p.name for p in written]
    assert names == ["orbit_000_sky.png", "orbit_001_sky.png", "orbit_sky.mp4"]
    assert read_raw(tmp_path / "orbit" / "orbit_000_sky.png").shape[:2] == (40, 40)
    err = main(["relight", "--run", str(no_prior_run), "--env", "sky", "--out", str(tmp_path), "--resolution", "4"])
    assert err == 2 and "--resolution 4: choose 8 to 8192 pixels" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--views", "orbit", "--frames", "0"], "--frames 0: give 1 or more"),
        (["--views", "orbit", "--fps", "0"], "--fps 0: give 1 or more"),
        (["--env-height", "2"], "--env-height 2: give 4 or more"),
    ],
)
def test_a_count_out_of_range_names_its_own_flag(tmp_path, capsys, flags, message):
    from matspray.cli import main

    argv = ["relight", "--run", str(tmp_path / "run"), "--env", "sky", "--out", str(tmp_path / "out"), *flags]
    assert main(argv) == 2
    assert capsys.readouterr().err == f"matspray relight: error: {message}\n"
