"""Each setting is declared once: its default, help and flag on its dataclass field (`matspray.settings.setting`);
a preset only changes defaults (a partial config, checked against the fields); a command's parser takes a setting's
flag, help and default from its field and offers no second way to set it."""

from __future__ import annotations

import argparse
from dataclasses import MISSING, fields, is_dataclass

import pytest

from matspray import presets
from matspray.cli import build_parser
from matspray.cli.options import flagged_fields
from matspray.cli.settings import _dataclass_of, _hints, settings_table
from matspray.errors import ConfigError
from matspray.method.config import PipelineConfig, build_config, preset_paths, preset_settings
from matspray.settings import flag_of, help_of, setting

# the command's predictor spec: `auto` (chosen per dataset) and its options, which the predictor registry describes
COMMAND_DECLARED = {"--predictor", "--weights"}


def walk(cls=PipelineConfig, prefix: str = ""):
    """(dotted name, field, the field's class) of every field of the config and its sections."""
    hints = _hints(cls)
    for f in fields(cls):
        yield prefix + f.name, f, cls
        section = _dataclass_of(hints[f.name])
        if section is not None:
            yield from walk(section, f"{prefix}{f.name}.")


def defaults() -> dict:
    """Every field's default by dotted name (a section's as made by its factory)."""
    config, values = PipelineConfig(), {}
    for name, f, _ in walk():
        target = config
        for part in name.split("."):
            target = getattr(target, part, None) if target is not None else None
        values[name] = target if not is_dataclass(target) else None
    return values


def commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def test_every_field_declares_its_help_on_itself():
    declared = [name for name, f, _ in walk() if help_of(f)]
    assert len(declared) > 90
    assert not [name for name, f, _ in walk() if not help_of(f)]
    table = settings_table()
    assert all(setting.meaning for setting in table.values())
    assert not any("TODO" in setting.meaning for setting in table.values())


def test_a_setting_without_help_is_refused():
    with pytest.raises(ValueError, match="needs its help"):
        setting(1)


def test_no_preset_declares_a_name_that_is_no_setting_or_repeats_a_default():
    known = defaults()
    for preset, partial in presets.PRESET_SETTINGS.items():
        for path, value in preset_settings(preset).items():
            assert path in known, (preset, path)
            assert value != known[path], f"{preset} sets {path} to its default {value}: declared twice"
    assert presets.PRESET_SETTINGS["demo"] == {}  # the dataclasses' defaults are the demo preset
    assert preset_paths({"refine": {"merger": {"hidden": 64}}}) == {"refine.merger.hidden": 64}


@pytest.mark.parametrize(
    "partial, problem",
    [
        ({"refine": {"iteration": 30}}, r"refine\.iteration is no setting"),
        ({"lift": {"samples_per_side": 2.5}}, r"lift\.samples_per_side = 2\.5 is not a int"),
        ({"seed": {"x": 1}}, r"seed\.x is no setting"),
    ],
)
def test_a_preset_is_checked_against_the_fields(monkeypatch, partial, problem):
    monkeypatch.setitem(presets.PRESET_SETTINGS, "test", partial)
    with pytest.raises(ConfigError, match=problem):
        build_config("test")


def test_no_parser_declares_a_setting_a_second_time():
    declared = flagged_fields()
    research = {key.replace(".", "_") for key in settings_table()} | set(settings_table())
    for name, parser in commands().items():
        if "--set" not in shown_flags(parser):
            continue  # info and predict read photos at a factor of their own (`--downscale`, default 1), not a run's
        for action in parser._actions:
            for flag in action.option_strings:
                field = declared.get(flag)
                if field is None or flag in COMMAND_DECLARED:
                    continue
                assert action.help.startswith(help_of(field)), (name, flag, "help written twice")
                assert action.default in (None, field.default), (name, flag, "default written twice")
            # a research setting has one way in: --set KEY=VALUE
            assert action.dest not in research or not action.option_strings, (name, action.option_strings)


def shown_flags(parser) -> set[str]:
    return {s for a in parser._actions if a.help != argparse.SUPPRESS for s in a.option_strings}


def test_every_flag_is_declared_on_one_field_and_its_help_comes_from_there():
    flags = [flag_of(f) for _, f, _ in walk() if flag_of(f)]
    assert len(flags) == len(set(flags))
    run = commands()["run"]
    options = {s: a for a in run._actions for s in a.option_strings}
    for flag in ("--downscale", "--object-bounds", "--device", "--backend", "--preset", "--method"):
        field = flagged_fields()[flag]
        assert options[flag].help.startswith(help_of(field))
        assert options[flag].default in (None, field.default) and field.default is not MISSING
    assert set(settings_table()).isdisjoint(f.name for f in flagged_fields().values())  # not also a --set key
