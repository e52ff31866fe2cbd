"""Research settings by their dotted names: `--set lift.min_support=0.5 refine.normal_lr=0`, and
`matspray run --list-settings`, which prints every key with its default and meaning.

The keys are the fields of `matspray.method.config.PipelineConfig` and of its sections' dataclasses (geometry, lift,
refine, refine.merger, visibility), found by walking them, so a field added to a section is settable without a
change here; its meaning is the comment beside (or just above) the field in the source. A value is read by the
field's type (int, float, on/off, text, none where the field may be None, comma-separated numbers for tuples);
the library validates it, and a bad one comes back naming `--set KEY`.

Nothing here imports torch at import time: the parsers stay fast."""

from __future__ import annotations

import argparse
import inspect
import math
import os
import re
import types
import typing
from dataclasses import dataclass, fields, is_dataclass

from matspray.errors import ConfigError

# set by their own flags (or by nothing: the preset's and the seed's copies inside the geometry section)
OWN_FLAGS = {
    "preset": "--preset",
    "method": "--method",
    "predictor": "--predictor",
    "predictor_options": "--weights",
    "device": "--device",
    "backend": "--backend",
    "downscale": "--downscale",
}
# follow --preset and seed, or are set per variant by the pipeline (matspray.method.pipeline.refine_config)
DERIVED = ("geometry.preset", "geometry.seed", "refine.variant", "refine.seed")
# a field's comment goes on in the comment lines below it while it is unfinished: a parenthesis left open, or a last
# word that cannot end a phrase (otherwise those lines are the next field's)
UNFINISHED = (
    ",",
    ";",
    ":",
    "(",
    " the",
    " a",
    " an",
    " of",
    " and",
    " or",
    " to",
    " in",
    " by",
    " it",
    " is",
    " are",
    " not",
    " be",
)
UNFINISHED += (" with", " for", " from", " as", " at", " on", " than", " that", " which", " when", " where")
# meanings of fields whose source has no comment (a field with one uses its own)
MEANINGS = {
    "geometry.iterations": "Gaussian Splatting steps (the preset's; the densification schedule follows)",
    "geometry.max_gaussians": "cap on the Gaussians densification may grow to (lower it when a GPU runs out of memory)",
    "refine.iterations": "refinement steps of each variant (the preset's)",
    "seed": "random seed of the run (geometry, predictor draws, refinement unless refine_seed)",
    "geometry.init_opacity": "opacity of the initial Gaussians",
    "geometry.init_scale": "initial size, in multiples of the spacing of the neighbouring points",
    "geometry.sh_degree": "highest spherical-harmonics degree of the colours",
    "geometry.lr_means_final": "learning rate of the positions at the last step (exponential decay from lr_means)",
    "geometry.lr_sh_dc": "learning rate of the colours' constant term",
    "geometry.lr_sh_rest": "learning rate of the colours' higher SH terms",
    "geometry.lr_opacity": "learning rate of the opacities",
    "geometry.lr_scales": "learning rate of the (log) scales",
    "geometry.lr_quats": "learning rate of the rotations",
    "geometry.densify_until": "last step of densification",
    "geometry.densify_every": "steps between densifications",
    "geometry.opacity_reset_every": "steps between opacity resets",
    "geometry.prune_opacity": "Gaussians less opaque than this are pruned",
    "geometry.checkpoint_every": "steps between checkpoints (a rerun resumes from the last)",
    "refine.envmap_lr": "learning rate of the estimated light's log radiance",
    "refine.merger.hidden": "width of the merger's hidden layers",
    "refine.merger.layers": "hidden layers of each merger MLP",
    "refine.merger.softmax": "weights by a softmax over the views (off: the paper's ablation without it)",
}
SHADOWS = "shadows"  # on: the preset's shadow maps (the visibility section), off: none


@dataclass(frozen=True)
class Setting:
    key: str  # dotted name, e.g. lift.min_support
    hint: object  # the field's type
    meaning: str  # one line


def _hints(cls) -> dict:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # a forward reference that does not resolve: the annotations as written
        return {f.name: f.type for f in fields(cls)}


def _dataclass_of(hint):
    """The dataclass a field holds (also `X | None`), or None."""
    if is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):
        if is_dataclass(arg):
            return arg
    return None


def wrapped(text: str) -> bool:
    """Whether a comment goes on in the next comment line: a parenthesis is open, or it stops mid-phrase."""
    return text.count("(") > text.count(")") or text.rstrip().endswith(UNFINISHED)


def field_comments(cls) -> dict[str, str]:
    """Field name -> its comment: beside it (wrapped onto the next lines while they are full), inside its
    parenthesised default, or else the block just above it."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    comments, above, owner, continuing = {}, [], None, False
    for i, line in enumerate(lines):
        stripped = line.strip()
        if stripped.startswith("#"):
            text = stripped.lstrip("# ").strip()
            if continuing and owner is not None:  # the wrapped end of the field's own comment
                comments[owner] += " " + text
                continuing = wrapped(comments[owner])
            else:
                above.append(text)
            continue
        match = re.match(r"^    (\w+)\s*:", line)
        if not match or line.startswith("     "):
            if not stripped:
                above, owner, continuing = [], None, False
            elif stripped.startswith(")"):
                pass  # the end of a parenthesised default: its comment may go on below
            elif "# " in stripped and owner is not None:  # inside a parenthesised default
                comments[owner] = (comments[owner] + " " + stripped.split("# ", 1)[1]).strip()
                continuing = wrapped(comments[owner])
            continue
        owner, continuing = match.group(1), False
        if "  # " in line:
            comments[owner] = line.split("  # ", 1)[1].strip()
            continuing = wrapped(comments[owner])
        else:
            comments[owner] = ""
        if not comments[owner]:
            comments[owner] = " ".join(above)
        above = []
    return {name: " ".join(text.split()) for name, text in comments.items()}


def settings_table() -> dict[str, Setting]:
    """Every settable key, in the dataclasses' field order."""
    from matspray.method.config import PipelineConfig

    table: dict[str, Setting] = {}

    def walk(cls, prefix: str) -> None:
        hints, comments = _hints(cls), field_comments(cls)
        for f in fields(cls):
            key = prefix + f.name
            if key in OWN_FLAGS or key in DERIVED:
                continue
            hint = hints.get(f.name, f.type)
            section = _dataclass_of(hint)
            if section is not None:
                if key == "visibility":
                    table[SHADOWS] = Setting(
                        SHADOWS,
                        bool,
                        "bake each Gaussian's visibility and shadow the PBR "
                        "shading with it (off: the paper's unshadowed split-sum shading)",
                    )
                walk(section, key + ".")
                continue
            table[key] = Setting(key, hint, comments.get(f.name) or MEANINGS.get(key, ""))

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
        if key in OWN_FLAGS:
            raise OwnFlagError(key, OWN_FLAGS[key])
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
def add_set_argument(parser, example: str = "lift.min_support=0.5 refine.normal_lr=0") -> None:
    parser.add_argument(
        "--set",
        dest="overrides",
        nargs="+",
        action="extend",
        default=[],
        metavar="KEY=VALUE",
        help=f"research settings by name, e.g. --set {example} (`matspray run --list-settings` lists every key "
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
        meaning = setting.meaning or "(no comment in the source)"
        if key.startswith("visibility."):
            meaning = f"with shadows=on: {meaning}"
        lines.append(f"{key} = {show_value(default)}  [{type_name(setting.hint)}]  {meaning}")
    return "\n".join(lines)
