"""One name per concept on the command line: every parser walked, the options each shows, the old names that
still parse, and the research settings reached by `--set KEY=VALUE` and listed by `run --list-settings`."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from matspray.cli import build_parser, main
from matspray.cli.options import build_config_from_args
from matspray.cli.settings import settings_table

MAX_OPTIONS = 15
# concept -> the flag every command uses for it
CANONICAL = {
    "run folder": "--run",
    "dataset folder": "--data",
    "lights to render under": "--env",
    "image size in pixels": "--resolution",
    "texture size in pixels": "--texture-resolution",
    "seed of a benchmark object": "--object-seed",
}
# names a concept had before, which must appear in no help (they still parse: test below)
OLD_NAMES = {"--res", "--max-size", "--texture-size", "--relight", "--relight-envs", "--no-ray"}
# the flags that once set research settings one by one: gone (`--set KEY=VALUE` sets each)
RESEARCH_FLAGS = {"--min-support", "--geometry-iterations", "--refine-iterations", "--light-warmup", "--shadows"}
RESEARCH_FLAGS |= {"--iterations"}  # geometry's, now --set geometry.iterations=N
# a command's positional that names a concept with a flag elsewhere
OLD_POSITIONALS = {"run", "run_positional", "data_positional"}


def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def shown(parser) -> list[argparse.Action]:
    return [a for a in parser._actions if not isinstance(a, argparse._HelpAction) and a.help != argparse.SUPPRESS]


def test_every_command_shows_at_most_15_options():
    counts = {name: len(shown(parser)) for name, parser in subparsers().items()}
    assert max(counts.values()) <= MAX_OPTIONS, counts
    assert counts["run"] == 15  # the largest: the method's research settings are behind --set


def test_no_research_flag_or_old_name_is_in_any_help():
    research = RESEARCH_FLAGS
    for name, parser in subparsers().items():
        flags = {s for a in shown(parser) for s in a.option_strings}
        if name == "predict":  # its --seed is the predictor's own (marigold's noise, simulated's draws), not a run's
            flags.discard("--seed")
        assert not flags & (research | OLD_NAMES | {"--shadows"}), (name, sorted(flags & (research | OLD_NAMES)))
        assert not {a.dest for a in shown(parser) if not a.option_strings} & OLD_POSITIONALS, name
        text = parser.format_help()
        for flag in RESEARCH_FLAGS:
            assert flag not in text, (name, flag)


def test_the_same_flag_means_the_same_setting_in_every_command():
    dests: dict[str, set] = {}
    for parser in subparsers().values():
        for action in shown(parser):
            for flag in action.option_strings:
                dests.setdefault(flag, set()).add(action.dest)
    assert {flag: d for flag, d in dests.items() if len(d) > 1} == {}
    for concept, flag in CANONICAL.items():
        assert flag in dests, concept
    # the commands that take a run or a dataset all take it by the same flag
    for name, parser in subparsers().items():
        for action in shown(parser):
            if action.dest in ("run", "data"):
                assert action.option_strings == [f"--{action.dest}"], (name, action.option_strings)


@pytest.mark.parametrize(
    "argv, dest, value",
    [
        (["synth", "--out", "o", "--res", "64"], "resolution", 64),
        (["synth", "--out", "o", "--resolution", "64"], "resolution", 64),
        (["synth", "--out", "o", "--seed", "3"], "object_seed", 3),
        (["colmap", "photos", "--out", "o", "--max-size", "800"], "resolution", 800),
        (["colmap", "photos", "--out", "o", "--resolution", "800"], "resolution", 800),
        (["export", "--run", "r", "--out", "f.glb", "--texture-size", "256"], "texture_size", 256),
        (["export", "--run", "r", "--out", "f.glb", "--texture-resolution", "256"], "texture_size", 256),
        (["eval", "--run", "r", "--relight", "sky", "city"], "env", ["sky", "city"]),
        (["eval", "--run", "r", "--env", "sky", "city"], "env", ["sky", "city"]),
        (["view", "runs/x"], "run_positional", "runs/x"),
        (["info", "data"], "data_positional", "data"),
        (["batch", "a", "b", "--out", "o"], "data_positional", ["a", "b"]),
        (["batch", "--data", "a", "b", "--out", "o", "--no-ray"], "no_ray", True),
    ],
)
def test_old_names_still_parse_into_the_same_setting(argv, dest, value):
    args = build_parser().parse_args(argv)
    got = getattr(args, dest)
    got = [str(v) for v in got] if isinstance(got, list) else str(got) if hasattr(got, "parts") else got
    assert got == value


def run_args(*argv):
    return build_parser().parse_args(["run", "--data", "d", "--out", "o", *argv])


def test_set_reaches_any_setting_and_the_old_research_flags_are_gone(capsys):
    config = build_config_from_args(
        run_args("--set", "lift.min_support=0.25", "geometry.normal_weight=0.1", "refine.normal_lr=0", "seed=4"),
        predictor="none",
    )
    assert config.lift.min_support == 0.25 and config.geometry.normal_weight == 0.1
    assert config.refine.normal_lr == 0.0 and config.seed == 4 and config.geometry.seed == 4
    for flag in sorted(RESEARCH_FLAGS):  # each research setting has one way in: --set
        with pytest.raises(SystemExit):
            run_args(flag, "1")
        assert f"unrecognized arguments: {flag} 1" in capsys.readouterr().err
    config = build_config_from_args(
        run_args("--set", "shadows=on", "visibility.rows=4", "lift.footprint_sigmas=none", "refine.merger.softmax=off")
    )
    assert config.visibility.rows == 4 and config.lift.footprint_sigmas is None and not config.refine.merger.softmax


def test_every_geometry_field_is_a_key_and_reaches_the_config():
    from matspray.geometry.config import GeometryConfig

    keys = settings_table()
    for field in dataclasses.fields(GeometryConfig):
        if field.name in ("preset", "seed"):  # follow --preset and seed
            continue
        assert f"geometry.{field.name}" in keys, field.name
    if "geometry.predicted_normal_weight" in keys:
        config = build_config_from_args(run_args("--set", "geometry.predicted_normal_weight=0.2"))
        assert config.geometry.predicted_normal_weight == 0.2


@pytest.mark.parametrize(
    "words, message",
    [
        (["lift.min_support=abc"], "matspray run: error: --set lift.min_support: cannot read 'abc' as float"),
        (["lift.min_support=-1"], "matspray run: error: --set lift.min_support: must be in [0, 1], got -1.0"),
        (
            ["lift.bogus=1"],
            "matspray run: error: --set lift.bogus: no such setting here (matspray run --list-settings ",
        ),
        (["lift.min_support"], "matspray run: error: --set takes KEY=VALUE, got 'lift.min_support' (matspray run "),
        (["device=cpu"], "matspray run: error: --set device: has its own flag, --device"),
        (
            ["refine.merger.softmax=maybe"],
            "matspray run: error: --set refine.merger.softmax: cannot read 'maybe' as on|off",
        ),
        # NaN would pass every `>= 0` check and compare as "off" wherever a weight is tested with `> 0`
        (
            ["geometry.predicted_normal_weight=nan"],
            "matspray run: error: --set geometry.predicted_normal_weight: must be a finite number, got 'nan'",
        ),
        (["refine.normal_lr=inf"], "matspray run: error: --set refine.normal_lr: must be a finite number, got 'inf'"),
        (  # float | None: "none" is None, a number must be finite
            ["lift.footprint_sigmas=nan"],
            "matspray run: error: --set lift.footprint_sigmas: must be a finite number, got 'nan'",
        ),
    ],
)
def test_bad_set_words_are_one_line(tmp_path, capsys, words, message):
    assert main(["run", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--set", *words]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1, err
    assert not (tmp_path / "run").exists()


def test_list_settings_prints_every_key_with_its_default_and_meaning(capsys):
    with pytest.raises(SystemExit) as done:
        main(["run", "--preset", "test", "--list-settings"])
    assert done.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "settings of `matspray run --set KEY=VALUE` (defaults: --preset test --method matspray)"
    listed = {line.split(" = ")[0]: line for line in lines[2:]}
    assert set(listed) == set(settings_table())
    assert listed["refine.iterations"].startswith("refine.iterations = 30  [int]  ")  # the test preset's
    assert listed["lift.min_support"].startswith("lift.min_support = 0.5  [float]  a view sees a Gaussian")
    assert all(line.split("]  ", 1)[1].strip() for line in lines[2:])  # each has a meaning
    with pytest.raises(SystemExit):
        main(["run", "--method", "paper", "--list-settings"])
    assert "lift.min_support = 0.0  [float]" in capsys.readouterr().out
