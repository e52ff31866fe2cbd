"""The method's command-line options, shared by `run`, `demo`, `bench` and `batch`: each flag sets one named
setting of `matspray.method.config` (the library validates; a bad value comes back as a SettingError, and
`matspray.cli.main` names the flag that set it). Nothing here imports torch, so `--help` stays fast.

A flag, its help and its default are declared on the setting's field (`matspray.settings.setting`); a command names
which of those flags it offers (`add_setting_flags`). The research settings are reached by name, `--set KEY=VALUE`
(`matspray.cli.settings`)."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

from matspray.cli.settings import NotFinite, field_hint, parse_value
from matspray.errors import ConfigError
from matspray.files import check_output_folder
from matspray.method.config import PipelineConfig
from matspray.presets import ADDITION_NAMES, METHODS, PRESETS, VARIANT_NAMES
from matspray.settings import flag_of, help_of

# the setting flags `run` offers (the research settings are behind --set), and those of every other command that
# computes (demo, bench, batch, and geometry, relight, eval, export, view outside a pipeline)
SETTING_FLAGS = ("--object-bounds", "--downscale", "--device", "--backend")
COMPUTE_FLAGS = ("--device", "--backend")


def flagged_fields() -> dict:
    """PipelineConfig's fields with a flag of their own, by flag."""
    return {flag_of(f): f for f in fields(PipelineConfig) if flag_of(f)}


def add_setting_flags(parser, flags) -> None:
    """The options `flags` (each a flag declared on a field of PipelineConfig), with the field's help; each parses to
    None when not given (the field's default then holds, `method_settings_from_args`)."""
    known = flagged_fields()
    for flag in flags:
        metavar = flag.lstrip("-").split("-")[-1].upper()
        parser.add_argument(flag, dest=known[flag].name, metavar=metavar, help=help_of(known[flag]))


def add_choice_argument(parser, name: str, choices, **kwargs) -> None:
    """`--preset` or `--method` (the field `name`'s flag): its choices, its default and help from the field."""
    f = next(f for f in fields(PipelineConfig) if f.name == name)
    parser.add_argument(
        flag_of(f), choices=choices, default=f.default, help=f"{help_of(f)}; default {f.default}", **kwargs
    )


VARIANT_HELP = "which asset of the run (default: full, else photos-only when the run has it, else the one it has)"


def add_compute_arguments(parser) -> None:
    """--device and --backend, for the commands that compute outside a pipeline (geometry, relight, eval, export)."""
    known = flagged_fields()
    for flag in COMPUTE_FLAGS:
        parser.add_argument(flag, default=known[flag].default, help=help_of(known[flag]))


def add_run_arguments(parser) -> None:
    """What `run` and `batch` take besides the method: the predictor, its options and the variants."""
    from matspray.predictors.kinds import add_run_option_flags, predictor_usage

    parser.add_argument(
        "--predictor",
        default="auto",
        metavar="SPEC",
        help=f"2D material maps: {predictor_usage()}, or none (no maps: the photos-only asset); default auto: "
        "simulated where the dataset has ground-truth maps, else none",
    )
    parser.add_argument(
        "--variant",
        choices=VARIANT_NAMES,
        nargs="+",
        default=None,
        help="method variants to refine (the paper's ablations; without 2D maps no-prior, the paper's baseline, and "
        "photos-only, a dielectric unless the photos show metal); default: full, or photos-only with --predictor none",
    )
    add_run_option_flags(parser)  # the predictors' options `run` offers (`matspray.predictors.kinds`)


def predictor_options_from_args(args) -> dict:
    """PredictorOptions fields from the predictors' flags given."""
    from matspray.predictors.kinds import run_options_from_args

    return run_options_from_args(args)


def output_folder(value: str):
    """An --out folder, checked as the command line is read (before any work): refused in one line when it is a
    file, when a folder on its way is one, or when it cannot be made there; the command makes it."""
    path = Path(value)
    try:
        return check_output_folder(path, path)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def given(args, flags) -> list[str]:
    """Which of `flags` the command line gave (a flag left at None, [] or off was not)."""
    return [flag for flag in flags if getattr(args, flag.lstrip("-").replace("-", "_")) not in (None, [], False)]


def refuse(flags: list[str], what: str) -> None:
    """Flags that nothing would read are refused, not ignored: '<flags> is|are <what>'."""
    if flags:
        from matspray.errors import ConfigError

        raise ConfigError(f"{' and '.join(flags)} {'is' if len(flags) == 1 else 'are'} {what}")


def hidden_alias(parser, flag: str, dest: str, **kwargs) -> None:
    """An old name of a flag: it still parses (into `dest`), shown in no help."""
    parser.add_argument(flag, dest=dest, help=argparse.SUPPRESS, default=argparse.SUPPRESS, **kwargs)


def add_method_arguments(parser, presets=PRESETS, flags=COMPUTE_FLAGS) -> None:
    """--preset, --method, --without, and the setting flags `flags` (`SETTING_FLAGS` for `run`); the research settings
    are reached by `--set` (`add_set_argument`)."""
    add_choice_argument(parser, "preset", presets)
    add_choice_argument(parser, "method", METHODS)
    group = parser.add_argument_group(
        "method settings (default: the method's; each matspray addition has its own switch)"
    )
    group.add_argument(
        "--without",
        nargs="+",
        choices=ADDITION_NAMES,
        default=(),
        metavar="ADDITION",
        help=f"switch single additions of matspray off: {', '.join(ADDITION_NAMES)}",
    )
    add_setting_flags(group, flags)


def method_settings_from_args(args) -> dict:
    """{setting: value} for the setting flags the user gave (read by the field's type)."""
    from matspray.errors import SettingError

    settings, known = {}, flagged_fields()
    for f in (known[flag] for flag in SETTING_FLAGS):
        text = getattr(args, f.name, None)
        if text is None:
            continue
        try:
            settings[f.name] = parse_value(text, field_hint(PipelineConfig, f.name))
        except NotFinite as exc:
            raise SettingError(f.name, str(exc)) from None
        except ValueError:
            raise SettingError(f.name, f"cannot read {text!r}") from None
    return settings


def build_config_from_args(args, **fixed):
    """The run's PipelineConfig from the parsed flags and `--set` (`fixed`: settings the command sets itself)."""
    from matspray.cli.settings import settings_from_overrides
    from matspray.method.config import build_config

    named = settings_from_overrides(getattr(args, "overrides", None), args.preset)
    return build_config(
        args.preset, args.method, tuple(args.without), **{**method_settings_from_args(args), **named, **fixed}
    )


def flag_of_setting(setting: str, parser=None) -> str | None:
    """The option of `parser` that sets `setting`: the first shown one whose destination is the setting's name (a
    section of another command's config, as `export.`, left out), else the flag declared on PipelineConfig's field
    (`--weights`, `--set shadows`), else None."""
    head, _, tail = setting.partition(".")
    sections = {f.name for f in fields(PipelineConfig)}
    names = {setting.replace(".", "_")} | ({tail} if tail and head not in sections else set())
    actions = [a for a in (parser._actions if parser else []) if a.dest in names and a.option_strings]
    for action in sorted(actions, key=lambda a: a.help == argparse.SUPPRESS):  # shown ones first
        return action.option_strings[0]
    return next((flag_of(f) for f in fields(PipelineConfig) if f.name == setting), None)


def flag_message(error, command: str | None = None, parser=None) -> str:
    """An error's one-line message; a SettingError names the flag of `command` (its `parser`; without one, a flag
    declared on PipelineConfig's fields) that set the setting (`--set KEY` for a research setting). A message never
    points at a flag the command lacks (`--set downscale` in a command without --downscale is no setting of it, not
    'use --downscale')."""
    flags = shown_flags(parser) if parser is not None else None
    own = getattr(error, "flag", None)  # settings.OwnFlagError: --set KEY of a setting that a flag sets
    if own is not None and flags is not None and own not in flags:
        return f"--set {error.key}: `matspray {command}` has no such setting ({own} is a flag of `matspray run`)"
    setting = getattr(error, "setting", None)
    if setting is None:
        return str(error)
    flag = flag_of_setting(setting, parser) or f"--set {setting}"
    if flags is not None and flag.split()[0] not in flags:
        flag = f"--set {setting}" if "--set" in flags else setting
    return f"{flag}: {error.problem}"


def shown_flags(parser) -> set[str]:
    """The options a command's parser shows in its help (hidden old names are not pointed at)."""
    return {s for a in parser._actions if a.help != argparse.SUPPRESS for s in a.option_strings}
