"""Research settings by their dotted names: `--set lift.min_support=0.5 refine.normal_lr=0`, and
`matspray run --list-settings`, which prints every key with its default and meaning.

The keys are the fields of `matspray.method.config.PipelineConfig` and of its sections' dataclasses (geometry, lift,
refine, refine.merger, visibility), found by walking them, so a field added to a section is settable without a
change here; its meaning is the help declared on the field (`matspray.settings.setting`). A field with a flag of its
own (`--downscale`, ...) is set by that flag, not by `--set`; an internal one (it follows another setting) by neither.
A value is read by the field's type (int, float, on/off, text, none where the field may be None, comma-separated
numbers for tuples); the library validates it, and a bad one comes back naming `--set KEY`.

Nothing here imports torch at import time: the parsers stay fast."""

from __future__ import annotations

import argparse
import math
import os
import sys
import types
import typing
from dataclasses import dataclass, fields, is_dataclass

from matspray.errors import ConfigError
from matspray.method.config import PipelineConfig
from matspray.settings import flag_of, help_of, internal

SHADOWS = "shadows"  # on: the preset's shadow maps (the visibility section), off: none


def own_flags() -> dict[str, str]:
    """PipelineConfig's settings that a flag of their own sets: {setting: flag} (`--set KEY` refuses them)."""
    return {f.name: flag_of(f) for f in fields(PipelineConfig) if flag_of(f) and not flag_of(f).startswith("--set")}


@dataclass(frozen=True)
class Setting:
    key: str  # dotted name, e.g. lift.min_support
    hint: object  # the field's type
    meaning: str  # one line


def field_hint(cls, name: str):
    """The type of the field `name` of `cls`, read from its annotation alone (the rest of the class's annotations may
    name sections whose modules are not imported)."""
    annotation = next(f.type for f in fields(cls) if f.name == name)
    if not isinstance(annotation, str):
        return annotation
    return eval(annotation, vars(sys.modules[cls.__module__]))  # noqa: S307 - a field's own annotation


def _hints(cls) -> dict:
    """The fields' types; PipelineConfig's name the sections' classes, imported here."""
    if cls is PipelineConfig:
        from matspray.method.config import section_types

        return typing.get_type_hints(cls, localns=section_types())
    return typing.get_type_hints(cls)


def _dataclass_of(hint):
    """The dataclass a field holds (also `X | None`), or None."""
    if is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):
        if is_dataclass(arg):
            return arg
    return None


def settings_table() -> dict[str, Setting]:
    """Every settable key, in the dataclasses' field order."""
    table: dict[str, Setting] = {}

    def walk(cls, prefix: str) -> None:
        hints = _hints(cls)
        for f in fields(cls):
            key, section = prefix + f.name, _dataclass_of(hints[f.name])
            if key == "visibility":  # on/off by its own key; its fields size the shadow maps where it is on
                table[SHADOWS] = Setting(SHADOWS, bool, help_of(f))
            elif internal(f) or (flag_of(f) and section is None):
                continue
            if section is not None:
                walk(section, key + ".")
                continue
            meaning = help_of(f)
            table[key] = Setting(key, hints[f.name], meaning)

    walk(PipelineConfig, "")
    return table


# ------------------------------------------------------------------------------------------ values
class NotFinite(ValueError):
    """A number that is NaN or infinite: no setting takes one (a weight of NaN would compare as off, silently)."""


def finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise NotFinite(f"must be a finite number, got {text.strip()!r}")
    return value


def parse_value(text: str, hint):
    """`text` as a value of type `hint`; ValueError when it is not one."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if text.strip().lower() == "none" and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return parse_value(text, arg)
            except NotFinite:
                raise
            except ValueError:
                continue
        raise ValueError(text)
    if origin is typing.Literal:
        for arg in args:
            if str(arg) == text:
                return arg
        raise ValueError(text)
    if hint is bool:
        words = {
            "on": True,
            "true": True,
            "yes": True,
            "1": True,
            "off": False,
            "false": False,
            "no": False,
            "0": False,
        }
        if text.strip().lower() not in words:
            raise ValueError(text)
        return words[text.strip().lower()]
    if hint is int:
        return int(text)
    if hint is float:
        return finite_float(text)
    if hint is str:
        return text
    if origin is tuple:
        element = args[0] if args else float
        return tuple(parse_value(part, element) for part in text.replace(",", " ").split())
    raise ValueError(f"cannot be set from the command line ({hint})")


def show_value(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, tuple):
        return ",".join(map(show_value, value))
    return str(value)


def type_name(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return "|".join("none" if a is type(None) else type_name(a) for a in args)
    if hint is bool:
        return "on|off"
    if origin is tuple:
        return "numbers"
    return getattr(hint, "__name__", str(hint))


class OwnFlagError(ConfigError):
    """`--set KEY` of a setting that a flag sets. Which command was given is the CLI's to say (`options.flag_message`
    names the flag where the command has it, and `run` where it has not)."""

    def __init__(self, key: str, flag: str):
        super().__init__(f"--set {key}: has its own flag, {flag}")
        self.key, self.flag = key, flag


def settings_from_overrides(items, preset: str, allowed=None) -> dict:
    """{dotted setting: value} from `--set KEY=VALUE ...` words (`allowed`: a predicate on keys, None = any)."""
    from matspray.errors import SettingError

    table = settings_table()
    settings = {}
    for item in items or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set takes KEY=VALUE, got {item!r} (matspray run --list-settings lists the keys)")
        own = own_flags()
        if key in own:
            raise OwnFlagError(key, own[key])
        if key not in table or (allowed is not None and not allowed(key)):
            raise SettingError(key, "no such setting here (matspray run --list-settings lists them)")
        try:
            value = parse_value(text, table[key].hint)
        except NotFinite as exc:
            raise SettingError(key, str(exc)) from None
        except ValueError:
            raise SettingError(key, f"cannot read {text!r} as {type_name(table[key].hint)}") from None
        if key == SHADOWS:
            from matspray.method.config import shadow_maps

            settings["visibility"] = shadow_maps(preset) if value else None
            continue
        if key == "light_probe" and value is not None:  # recorded in the run's config: from any directory
            value = os.path.abspath(os.path.expanduser(value))
        settings[key] = value
    return settings


# ------------------------------------------------------------------------------------------ flags
def add_set_argument(parser, example: str = "lift.min_support=0.5 refine.normal_lr=0", flag: str = "--set") -> None:
    """`--set KEY=VALUE ...` into `args.overrides` (`flag`: its name in a parser whose --set means something else)."""
    parser.add_argument(
        flag,
        dest="overrides",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help=f"research settings by name, e.g. {flag} {example} (`matspray run --list-settings` lists every key "
        "with its default and meaning)",
    )


class ListSettings(argparse.Action):
    """`--list-settings`: print the table for the --preset and --method given before it, and exit."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(settings_listing(getattr(namespace, "preset", "demo"), getattr(namespace, "method", "matspray")))
        parser.exit()


def settings_listing(preset: str = "demo", method: str = "matspray") -> str:
    """Every settable key with its default under `preset` and `method`, its type and its meaning."""
    from matspray.method.config import build_config, shadow_maps

    config = build_config(preset, method)
    lines = [f"settings of `matspray run --set KEY=VALUE` (defaults: --preset {preset} --method {method})", ""]
    for key, setting in settings_table().items():
        if key == SHADOWS:
            default = config.visibility is not None
        elif key.startswith("visibility."):
            source = config.visibility or shadow_maps(preset)
            default = getattr(source, key.split(".", 1)[1])
        else:
            default = config
            for part in key.split("."):
                default = getattr(default, part)
        meaning = setting.meaning
        if key.startswith("visibility."):
            meaning = f"with shadows=on: {meaning}"
        lines.append(f"{key} = {show_value(default)}  [{type_name(setting.hint)}]  {meaning}")
    return "\n".join(lines)
