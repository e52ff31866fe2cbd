"""What a newcomer meets first: `info` on a folder of photos, a dataset given where a run is expected,
and `--set` of a setting that a flag sets, in every command that takes `--set`."""

from __future__ import annotations

import argparse
import re

import pytest
import torch

from matspray.cli import build_parser, main
from matspray.cli.options import flag_message, shown_flags
from matspray.cli.settings import OwnFlagError, own_flags, settings_from_overrides, settings_table
from matspray.data.images import write_image
from matspray.errors import SettingError


def commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def test_info_on_a_folder_of_photos_says_what_it_sees_and_how_to_make_a_dataset(tmp_path, capsys):
    for i in range(66):
        write_image(tmp_path / f"IMG_{i:04d}.jpg", torch.rand(4, 6, 3))
    err = one_line_error(capsys, ["info", "--data", str(tmp_path)])
    assert f"{tmp_path}: holds 66 photos but no camera poses" in err
    assert f"`matspray colmap {tmp_path} --out DATA` makes a dataset of them" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["relight", "--env", "sky", "--out", "OUT"],
        ["view"],
        ["export", "--out", "OUT/x.glb"],
        ["eval"],
    ],
)
def test_a_dataset_given_as_a_run_is_named_a_dataset_with_the_run_that_makes_a_run(tmp_path, capsys, argv):
    if argv[0] == "export":
        pytest.importorskip("trimesh")
    dataset = tmp_path / "skull"
    dataset.mkdir()
    (dataset / "transforms_train.json").write_text('{"frames": []}')
    argv = [a.replace("OUT", str(tmp_path / "out")) for a in argv]
    err = one_line_error(capsys, [argv[0], "--run", str(dataset), *argv[1:]])
    assert f"{dataset}: is a dataset, not a run folder" in err, err
    assert f"`matspray run --data {dataset} --out RUN`" in err


def test_no_setting_of_any_command_points_at_a_flag_the_command_lacks():
    run_flags = shown_flags(commands()["run"])
    assert set(own_flags().values()) <= run_flags  # the messages say these are flags of `matspray run`
    # every research setting, every setting a flag sets, and every option's destination in any command
    settings = {*settings_table(), *own_flags(), "visibility"}
    settings |= {a.dest for parser in commands().values() for a in parser._actions if a.option_strings}
    walked = 0
    for name, parser in commands().items():
        flags = shown_flags(parser)
        for setting in settings:
            message = flag_message(SettingError(setting, "is wrong"), name, parser)
            named = message.split(":")[0].split()[0]
            assert named in flags or named == setting, (name, setting, message)
            walked += 1
        if "--set" not in flags:
            continue
        for key, flag in own_flags().items():
            with pytest.raises(OwnFlagError) as caught:
                settings_from_overrides([f"{key}=1"], "test")
            message = flag_message(caught.value, name, parser)
            of_this_command = re.sub(r"\(--[a-z-]+ is a flag of `matspray run`\)", "", message)
            for pointed in re.findall(r"--[a-z][a-z-]*", of_this_command):
                assert pointed in flags, (name, key, message)
            assert flag in message
            walked += 1
    assert walked > 100


def test_geometry_takes_downscale_as_run_does_and_uses_it(tmp_path, capsys, monkeypatch):
    data, out = str(tmp_path / "data"), str(tmp_path / "run")
    err = one_line_error(capsys, ["geometry", "--data", data, "--out", out, "--set", "downscale=2"])
    assert err == "matspray geometry: error: --set downscale: has its own flag, --downscale"
    err = one_line_error(capsys, ["geometry", "--data", data, "--out", out, "--set", "method=paper"])
    assert "--set method: `matspray geometry` has no such setting (--method is a flag of `matspray run`)" in err
    read = {}

    def load_scene(root, **kwargs):
        read.update(kwargs)
        raise SettingError("downscale", "must be a finite number >= 1, got 0.5")

    monkeypatch.setattr("matspray.data.load_scene", load_scene)
    err = one_line_error(capsys, ["geometry", "--data", data, "--out", out, "--downscale", "2"])
    assert read == {"downscale": 2.0, "max_size": 256}  # the photos `run --preset demo --downscale 2` reads
    assert err == "matspray geometry: error: --downscale: must be a finite number >= 1, got 0.5"
