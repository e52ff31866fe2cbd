"""docs/cli.md's reference, made from the argparse parsers of `matspray` (`benchmarks.tables` writes it): per command
its usage, what it does and every option, and the research settings `--set KEY=VALUE` takes."""

from __future__ import annotations

import os
from pathlib import Path


def cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def settings_reference() -> list[str]:
    """The research settings `--set KEY=VALUE` takes (`matspray run --list-settings`), defaults of the demo preset."""
    from matspray.cli.settings import settings_listing

    lines = [
        "## Research settings: `--set KEY=VALUE`",
        "",
        "What `matspray run --list-settings` prints (defaults of `--preset demo --method matspray`; "
        "`--preset` and `--method` before `--list-settings` show theirs). `run`, `demo`, `bench` and `batch` take "
        "every key, `geometry` the `geometry.*` keys and `seed`.",
        "",
        "| key | default | value | what it does |",
        "| --- | --- | --- | --- |",
    ]
    for line in settings_listing().splitlines()[2:]:
        key_default, _, rest = line.partition("  [")
        kind, _, meaning = rest.partition("]  ")
        key, _, default = key_default.partition(" = ")
        lines.append(f"| `{key}` | `{default}` | {cell(kind)} | {cell(meaning)} |")
    return lines + [""]


def table_cli(results: Path) -> str:
    """docs/cli.md's reference: per command its usage, what it does and every option, from the parsers."""
    import argparse as ap

    from matspray.cli import COMMANDS, build_parser

    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # usage lines wrapped alike on every terminal
    try:
        parser = build_parser()
        sub = next(a for a in parser._actions if isinstance(a, ap._SubParsersAction))
        lines = []
        for name, _, summary in COMMANDS:
            command = sub.choices[name]
            formatter = command._get_formatter()
            lines += [
                f"## `matspray {name}`",
                "",
                summary[0].upper() + summary[1:] + ".",
                "",
                "```",
                "\n".join(
                    line.removeprefix("usage: ").removeprefix("       ")
                    for line in command.format_usage().strip().splitlines()
                ),
                "```",
                "",
            ]
            for group in command._action_groups:
                actions = [  # the hidden old names and research flags are in no help, and not here either
                    a for a in group._group_actions if not isinstance(a, ap._HelpAction) and a.help != ap.SUPPRESS
                ]
                if not actions:
                    continue
                lines += [
                    f"{group.title[0].upper() + group.title[1:]}:",
                    "",
                    "| option | value | default | what it does |",
                    "| --- | --- | --- | --- |",
                ]
                for a in actions:
                    option = ", ".join(f"`{s}`" for s in a.option_strings) or f"`{a.metavar or a.dest}`"
                    if a.nargs == 0:
                        value = ""
                    elif a.choices is not None:
                        value = " | ".join(f"`{c}`" for c in a.choices) + (" ..." if a.nargs in ("+", "*") else "")
                    elif isinstance(a.metavar, tuple):  # a value and optional ones: `--splats FILE.glb [LIGHT]`
                        value = f"`{a.metavar[0]} [{' '.join(a.metavar[1:])}]`"
                    else:
                        value = (a.metavar or a.dest.upper()) + (" ..." if a.nargs in ("+", "*") else "")
                        value = f"`{value}`" if a.option_strings else ""
                    default = (
                        ""
                        if a.default in (None, False, ap.SUPPRESS) or a.nargs == 0 or a.required
                        else f"`{a.default}`"
                    )
                    required = "required; " if a.required and a.option_strings else ""
                    lines.append(
                        f"| {option} | {cell(value)} | {cell(default)} | "
                        f"{required}{cell(formatter._expand_help(a) if a.help else '')} |"
                    )
                lines.append("")
        lines += settings_reference()
        return "\n".join(lines).rstrip()
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
