"""How a setting is declared: once, on its field of a frozen config dataclass, with its default, its one-line help and,
where a command shows it as an option of its own, its flag:

    min_support: float = setting(0.5, "a view sees a Gaussian when it gets >= this share of its best view's hits")
    downscale: float | None = setting(None, "shrink images by this on load", flag="--downscale")

`matspray run --list-settings` and `--set KEY=VALUE` (`matspray.cli.settings`) walk these fields; the command-line
parsers take an option's help from them (`matspray.cli.options`). Plain values, no torch: the parsers stay fast."""

from __future__ import annotations

from dataclasses import MISSING, Field, field

HELP, FLAG, INTERNAL = "help", "flag", "internal"


def setting(default=MISSING, help: str = "", *, factory=MISSING, flag: str | None = None, internal: bool = False):
    """A dataclass field with its default (or `factory`), its help, its flag (an option of its own, e.g. "--downscale";
    None: reached by `--set KEY=VALUE`) and whether it is `internal` (follows another setting, or is set per stage by
    the pipeline: not a setting of the command line)."""
    if not help:
        raise ValueError("a setting needs its help")
    metadata = {HELP: " ".join(help.split()), FLAG: flag, INTERNAL: internal}
    if factory is not MISSING:
        return field(default_factory=factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def help_of(f: Field) -> str:
    return f.metadata.get(HELP, "")


def flag_of(f: Field) -> str | None:
    return f.metadata.get(FLAG)


def internal(f: Field) -> bool:
    return bool(f.metadata.get(INTERNAL))
