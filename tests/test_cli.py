"""The CLI: help works, info describes a dataset, bad input is one clear line and a non-zero exit."""

import subprocess
import sys

import pytest

from matspray.cli import main
from tests.conftest import run_cli
from tests.test_readers import blender_folder


def test_help_lists_commands():
    result = run_cli("--help")
    assert result.returncode == 0
    assert "info" in result.stdout and "relightable" in result.stdout


def test_info_describes_dataset(tmp_path):
    result = run_cli("info", blender_folder(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "format: blender" in result.stdout
    assert "train: 2 views, 40x30 px" in result.stdout
    assert "masks: 2 of 2" in result.stdout
    assert "no test views" in result.stdout  # the one problem this folder has


def test_info_bad_input_is_one_line_without_traceback(tmp_path):
    (tmp_path / "transforms_train.json").write_text("{oops")
    result = run_cli("info", tmp_path)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "transforms_train.json: malformed JSON" in lines[0]


def test_info_missing_path(tmp_path):
    result = run_cli("info", tmp_path / "nowhere")
    assert result.returncode == 2 and "nowhere: path does not exist" in result.stderr


def run_config(*argv):
    import argparse

    from matspray.cli.options import build_config_from_args
    from matspray.cli.run import add_run_parser

    parser = argparse.ArgumentParser()
    add_run_parser(parser)
    return build_config_from_args(parser.parse_args(["--data", "d", "--out", "o", *argv]))


def test_run_refines_the_base_color_by_l1_unless_told_scale_invariant():
    assert run_config().refine.basecolor_loss == "l1"
    assert run_config("--set", "refine.basecolor_loss=scale-invariant").refine.basecolor_loss == "scale-invariant"
    from matspray.errors import SettingError

    with pytest.raises(SettingError, match="refine.basecolor_loss: unknown loss 'l2'"):
        run_config("--set", "refine.basecolor_loss=l2")


def test_the_huber_base_color_loss_and_its_delta_come_from_their_flags():
    from matspray.cli.options import flag_message
    from matspray.errors import SettingError

    refine = run_config("--set", "refine.basecolor_loss=huber", "--set", "refine.basecolor_huber_delta=0.1").refine
    assert (refine.basecolor_loss, refine.basecolor_huber_delta) == ("huber", 0.1)
    assert run_config().refine.basecolor_huber_delta == 0.05
    with pytest.raises(SettingError) as error:
        run_config("--set", "refine.basecolor_loss=huber", "--set", "refine.basecolor_huber_delta=0")
    assert flag_message(error.value) == "--set refine.basecolor_huber_delta: must be > 0, got 0.0"


def test_both_methods_refine_normals_and_the_flags_set_the_rate_and_the_predicted_maps_weight():
    from matspray.cli.options import flag_message
    from matspray.errors import SettingError

    for method in ("matspray", "paper"):
        assert run_config("--method", method).refine.refines_normals  # the paper refines normals too
    refine = run_config("--set", "refine.normal_lr=0", "--set", "refine.predicted_normal_weight=0.5").refine
    assert not refine.refines_normals and refine.predicted_normal_weight == 0.5
    with pytest.raises(SettingError) as error:
        run_config("--set", "refine.normal_lr=-1")
    assert flag_message(error.value) == "--set refine.normal_lr: must be >= 0, got -1.0"


def test_refine_seed_overrides_the_seed_for_refinement_only():
    from matspray.method.config import variant_refine_config

    config = run_config("--set", "seed=3")
    assert variant_refine_config(config, "full").seed == 3
    config = run_config("--set", "seed=3", "--set", "refine_seed=7")
    assert variant_refine_config(config, "full").seed == 7
    assert variant_refine_config(config, "supervised").variant == "supervised"
    assert config.geometry.seed == 3


def test_demo_offers_the_paper_preset_and_refuses_it_without_a_gpu(tmp_path, monkeypatch):
    result = run_cli("demo", "--help")
    assert "{test,demo,quality,paper}" in result.stdout
    result = run_cli("demo", "--preset", "paper", "--out", tmp_path / "demo")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "paper is sized for one CUDA GPU" in result.stderr and "--device cpu" in result.stderr
    assert not (tmp_path / "demo").exists()
    # asked for on the CPU, or on a machine with a GPU, it runs the paper-sized demo
    import argparse

    import matspray.batch.demo
    from matspray.cli.batch import add_demo_parser, demo_main

    ran = []
    monkeypatch.setattr(matspray.batch.demo, "run_demo", lambda out, **kw: ran.append(kw) or tmp_path / "report.html")
    parser = argparse.ArgumentParser()
    add_demo_parser(parser)
    assert demo_main(parser.parse_args(["--preset", "paper", "--device", "cpu", "--out", str(tmp_path)])) == 0
    assert ran[0]["preset"] == "paper" and ran[0]["config"].preset == "paper"


def run_cli_without(module: str, *args):
    """The CLI in a process where `module` does not import (as where its extra is not installed)."""
    code = f"import sys; sys.modules[{module!r}] = None; from matspray.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, timeout=120)


def test_colmap_commands_without_pycolmap_say_which_extra_in_one_line(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    import torch

    from matspray.data.images import write_image

    for i in range(3):
        write_image(photos / f"p{i}.png", torch.rand(24, 32, 3))
    colmap_folder = tmp_path / "scene"
    (colmap_folder / "sparse" / "0").mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (colmap_folder / "sparse" / "0" / name).write_bytes(b"\0" * 8)
    for result in (
        run_cli_without("pycolmap", "colmap", photos, "--out", tmp_path / "out"),
        run_cli_without("pycolmap", "info", colmap_folder),
    ):
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "pip install 'matspray[colmap]'" in lines[0], lines
    assert not (tmp_path / "out").exists()


OUTPUT_FOLDER_COMMANDS = {  # every command whose --out is a folder it makes, with what else it must be given
    "run": ["--data", "DATA"],
    "geometry": ["--data", "DATA"],
    "predict": ["--data", "DATA", "--predictor", "none"],
    "relight": ["--run", "RUN", "--env", "sunset"],
    "synth": [],
    "colmap": ["PHOTOS"],
    "demo": [],
    "bench": [],
    "batch": ["--data", "DATA"],
}


def test_every_output_folder_under_a_file_is_refused_in_one_line_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file where the output's folder would go")
    for command, given in OUTPUT_FOLDER_COMMANDS.items():
        for out, message in ((blocker / "out", f"{blocker} is a file, not a folder"), (blocker, "is a file, not")):
            with pytest.raises(SystemExit) as exit_:
                main([command, *given, "--out", str(out)])
            code, err = exit_.value.code, capsys.readouterr().err
            assert code == 2 and message in err and "Traceback" not in err, (command, err)
            assert err.strip().splitlines()[-1].startswith(f"matspray {command}: error: argument --out:"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_a_run_folder_given_as_a_dataset_is_named_so_with_its_dataset(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "dataset.json").write_text('{"source": "/data/mug", "format": "blender"}')
    for argv in (["info", str(run)], ["run", "--data", str(run), "--out", str(tmp_path / "other")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{run}: is a MatSpray run folder, not a dataset (its dataset is /data/mug; a run folder goes to" in err
    (run / "dataset.json").write_text("{not json")
    assert main(["info", str(run)]) == 2
    assert "not a dataset (give the dataset folder it was made from" in capsys.readouterr().err


def test_an_unknown_flag_is_refused_by_the_command_that_was_given_it(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["eval", "--run", "RUN", "--lights", "nope"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith("usage: matspray eval ")
    assert err.endswith("matspray eval: error: unrecognized arguments: --lights nope\n")
    with pytest.raises(SystemExit):
        main(["--bogus"])
    assert capsys.readouterr().err.endswith("matspray: error: unrecognized arguments: --bogus\n")


def test_batch_refuses_dataset_folders_that_are_not_there_before_starting_workers(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("")
    argv = ["batch", "--data", str(tmp_path / "gone"), str(notes), str(tmp_path), "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    gone = tmp_path / "gone"
    assert err == f"matspray batch: error: --data: {gone}, {notes}: not a folder (give each object's dataset folder)\n"
    assert not (tmp_path / "out").exists()


def test_the_preset_help_names_the_quality_presets_own_sizes():
    from matspray.method.config import build_config

    quality = build_config("quality")
    help_text = " ".join(run_cli("run", "--help").stdout.split())
    sizes = f"{quality.geometry.max_gaussians:,}".replace(",", " ")
    assert f"quality ({quality.geometry.resolution} px, up to {sizes} Gaussians and" in help_text
    assert f"and {quality.refine.iterations} refinement steps" in help_text
