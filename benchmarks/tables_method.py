"""docs/method.md's table of the two methods, made from `matspray.presets` (the table the code reads): every setting
where `--method matspray` differs from `--method paper`, with the paper's value and its source, and the settings where
the text is silent and both take the released code's value. Written by `python -m benchmarks.tables`."""

from __future__ import annotations

from matspray.presets import ADDITIONS, RELEASED_VALUES


def resolved(config, path: str):
    """The value of the dotted setting `path` in a (nested) frozen config."""
    for name in path.split("."):
        config = getattr(config, name)
    return config


def shown(value) -> str:
    return f"`{value}`" if value is not None else "none"


def table_methods(results=None) -> str:
    """`| addition | setting | matspray (demo) | paper | the paper's value from |`, then the released code's values."""
    from matspray.method.config import build_config  # torch: only when this table is made

    ours, paper = build_config("demo"), build_config("demo", "paper")
    lines = [
        "| addition | what `matspray` does | setting | matspray (demo) | paper | the paper's value from |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for a in ADDITIONS:
        cells = (f"`{a.name}`", a.what, f"`{a.setting}`", shown(resolved(ours, a.setting)))
        lines.append("| " + " | ".join((*cells, shown(resolved(paper, a.setting)), a.source)) + " |")
    lines += ["", "Where the text is silent, both methods take the released code's value:", ""]
    lines += ["| setting | both methods | from |", "| --- | --- | --- |"]
    lines += [f"| `{path}` | {shown(value)} | {source} |" for path, value, source in RELEASED_VALUES]
    return "\n".join(lines)
