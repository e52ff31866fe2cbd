"""Predictors that declare themselves: a name, an options dataclass and how `--predictor` names it, without torch.

Each module of this package declares one predictor kind (`PredictorKind`) and `register`s it; `predictor_kinds()`
imports them all once. A kind's options are a dataclass whose fields default to None (the predictor's own default)
and carry their help in `setting(...)`: `matspray predict` offers one flag per field (`--batch-size` for
`batch_size`; a field several kinds share is one flag, its help says each kind's meaning), and `run` / `batch` the
fields a kind lists in `run_flags`. `build` makes the predictor and imports its implementation only then, so that
`matspray --help` reads the declarations without loading torch.

A spec string (`--predictor files:DIR`) is parsed once, into a `PredictorSpec`.

Adding a predictor: its implementation module and a declaration here (or both in one module of this package).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
from dataclasses import MISSING, dataclass, field, fields
from typing import Callable

NO_PREDICTOR = "none"  # a run without 2D maps: only the variants that need none (matspray.presets.MAPLESS)
AUTO_PREDICTOR = "auto"  # `run`'s default: simulated where the dataset has ground-truth maps (benchmarks), else none


@dataclass(frozen=True)
class PredictorSpec:
    """`--predictor KIND[:ARGUMENT]`, parsed: the kind (lower case) and its argument (e.g. files' folder)."""

    kind: str
    argument: str = ""

    @classmethod
    def parse(cls, spec) -> PredictorSpec:
        kind, _, argument = str(spec).partition(":")
        return cls(kind.strip().lower(), argument.strip())


def setting(help: str, type: type = str, metavar: str | None = None):  # noqa: A002 (argparse's names)
    """A field of a predictor's options: None by default (the predictor's own), `help` for its flag."""
    return field(default=None, metadata={"help": help, "type": type, "metavar": metavar})


@dataclass(frozen=True)
class PredictorKind:
    name: str  # what `--predictor` starts with
    usage: str  # how `--predictor`'s help names it and says what it is, e.g. "marigold (diffusers, from --weights)"
    options: type  # a dataclass of `setting` fields
    build: Callable  # (argument: str, options, notify) -> matspray.predictors.base.Predictor
    argument: str = ""  # "": takes no ':' argument; "optional"; else it needs one, and this says what it is
    needs_ground_truth: bool = False  # predicts from the dataset's true maps (benchmarks only)
    object_seed: bool = False  # given no seed, draws from a `matspray synth` object's own (`options_for_dataset`)
    reruns_for_eval: bool = False  # cheap and deterministic: evaluation predicts the test views with it too
    run_flags: tuple[str, ...] = ()  # option names `run` and `batch` offer too
    run_hidden: tuple[str, ...] = ()  # option names `run` and `batch` take but show in no help (benchmarks only)

    @property
    def option_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in fields(self.options))


_KINDS: dict[str, PredictorKind] = {}
_DISCOVERED: list[bool] = []


def register(kind: PredictorKind) -> PredictorKind:
    """Make `kind` known to `--predictor` (and its options to the command line); a kind of the same name is replaced."""
    for f in fields(kind.options):
        if f.default is not None or f.default_factory is not MISSING or "help" not in f.metadata:
            raise TypeError(f"{kind.name}: option {f.name} must be a `setting(...)` (default None, with help)")
    _KINDS[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    _KINDS.pop(name, None)


def predictor_kinds() -> dict[str, PredictorKind]:
    """Every declared kind by name (this package's modules imported once, in name order)."""
    if not _DISCOVERED:
        for module in sorted(m.name for m in pkgutil.iter_modules(__path__)):
            importlib.import_module(f"{__name__}.{module}")
        _DISCOVERED.append(True)
    return dict(_KINDS)


def predictor_usage() -> str:
    """The kinds as `--predictor`'s help lists them."""
    return ", ".join(kind.usage for kind in predictor_kinds().values())


def option_fields() -> dict[str, list]:
    """Every option name -> [(kind, field)] of the kinds that take it, in the kinds' order."""
    found: dict[str, list] = {}
    for kind in predictor_kinds().values():
        for f in fields(kind.options):
            found.setdefault(f.name, []).append((kind, f))
    return found


def add_option_flags(parser, names=None, hidden=()) -> None:
    """One flag per option (`names`: only those; `hidden`: shown in no help), grouped by the kinds that take it, the
    help of each kind that takes it joined."""
    groups: dict[str, object] = {}
    for name, users in option_fields().items():
        if names is not None and name not in names:
            continue
        kind_names = [kind.name for kind, _ in users]
        title = " and ".join(kind_names)
        if title not in groups:
            groups[title] = parser.add_argument_group(title)
        helps = [f.metadata["help"] for _, f in users]
        text = helps[0] if len(set(helps)) == 1 else "; ".join(f"{k}: {h}" for k, h in zip(kind_names, helps))
        flag, metadata = "--" + name.replace("_", "-"), users[0][1].metadata
        help_text = argparse.SUPPRESS if name in hidden else text
        groups[title].add_argument(flag, type=metadata["type"], metavar=metadata["metavar"], help=help_text)


def options_from_args(args, names=None) -> dict:
    """The options the command line gave (flags left at None were not), by name."""
    wanted = option_fields() if names is None else names
    return {name: getattr(args, name) for name in wanted if getattr(args, name, None) is not None}


def add_run_option_flags(parser) -> None:
    """The options `run` and `batch` offer: each kind's `run_flags`, and its `run_hidden` in no help."""
    kinds = predictor_kinds().values()
    hidden = {name for kind in kinds for name in kind.run_hidden}
    add_option_flags(parser, {name for kind in kinds for name in kind.run_flags} | hidden, hidden)


def run_options_from_args(args) -> dict:
    kinds = predictor_kinds().values()
    return options_from_args(args, [name for kind in kinds for name in (*kind.run_flags, *kind.run_hidden)])
