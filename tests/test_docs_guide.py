"""The user guide (docs/guide/) stays short and runs as written: every `matspray ...` command it shows, in a code
block or inline, parses with the real command-line parser; it holds no dated work log; and every path to a docs page
that the code, the tests, the Makefile or the docs name exists."""

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from matspray.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guide"
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
INLINE = re.compile(r"`([^`\n]+)`")
PROGRAM = re.compile(r"^(?:\$ )?(?:\S*/)?(?:matspray|python3? -m matspray)(?=\s|$)")


def guide_pages() -> list[Path]:
    return sorted(GUIDE.glob("*.md"))


def commands(text: str) -> list[str]:
    """Every `matspray ...` command line of a markdown text: the lines of its code blocks that start with the
    program (a trailing backslash joins the next line), and its inline code spans that do."""
    found = []
    for block in FENCE.findall(text):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            if PROGRAM.match(line.strip()):
                found.append(line.strip())
    prose = FENCE.sub("", text)
    for span in INLINE.findall(prose.replace("\\|", "|")):
        if PROGRAM.match(span.strip()):
            found.append(span.strip())
    return found


def guide_commands() -> list[tuple[str, str]]:
    return [(page.name, command) for page in guide_pages() for command in commands(page.read_text())]


def arguments(command: str) -> list[str]:
    """The words after the program, as a shell would split them (a trailing `# comment` dropped)."""
    words = shlex.split(command, comments=True)
    if words[0] == "$":
        words = words[1:]
    skip = 3 if words[0].startswith("python") else 1  # python -m matspray | matspray
    return words[skip:]


def test_the_guide_shows_commands_and_the_extractor_finds_both_kinds():
    found = guide_commands()
    assert len(found) >= 30, found
    sample = "```bash\nmatspray run --data d \\\n    --out r   # a comment\nls\n```\nThen `matspray view --run r`."
    assert [arguments(command) for command in commands(sample)] == [
        ["run", "--data", "d", "--out", "r"],
        ["view", "--run", "r"],
    ]


@pytest.mark.parametrize(("page", "command"), guide_commands())
def test_every_guide_command_parses(page, command):
    parser = build_parser()
    words = arguments(command)
    if len(words) == 1 and not words[0].startswith("-"):  # `matspray relight` in prose names a command
        choices = next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        assert words[0] in choices, f"{page}: `{command}`: no such command"
        return
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            args = parser.parse_args(words)
    except SystemExit as exc:  # argparse's error (status 2), or --help / --version / --list-settings (status 0)
        assert exc.code in (0, None), f"{page}: `{command}` does not parse: {err.getvalue().strip()}"
        return
    assert args.command is not None, f"{page}: `{command}` names no command"


def test_a_wrong_command_fails_the_check():
    parser = build_parser()
    with pytest.raises(SystemExit) as exc, contextlib.redirect_stderr(io.StringIO()):
        parser.parse_args(arguments("matspray export --run r --out f.glb --texture-size-typo 4"))
    assert exc.value.code == 2


def test_the_guide_is_short_and_holds_no_dated_log():
    pages = guide_pages()
    names = {page.name for page in pages}
    assert {"getting-started.md", "your-photos.md", "gpu.md", "viewer.md", "export.md", "cli-by-task.md"} <= names
    assert sum(len(page.read_text().splitlines()) for page in pages) <= 1000
    for page in pages:
        text = page.read_text()
        assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), f"{page.name}: a date; dated notes go in docs/dev/"
        assert not re.search(r"\bissue \d+|\bthis (change|session)\b", text, re.I), f"{page.name}: a work-log phrase"


def test_every_docs_path_named_in_code_exists():
    """A docs page's path (docs/..., ending in .md) named in a comment, docstring or help text of the package, the
    benchmarks, the tests, the Makefile or the docs exists (pages move: docs/guide/, docs/dev/)."""
    sources = [*ROOT.glob("matspray/**/*.py"), *ROOT.glob("benchmarks/**/*.py"), *ROOT.glob("tests/*.py")]
    sources += [ROOT / "Makefile", ROOT / "README.md", *ROOT.glob("docs/**/*.md")]
    named, missing = 0, []
    for path in sources:
        for name in re.findall(r"\bdocs/[\w./-]*?\.md\b", path.read_text()):
            named += 1
            if not (ROOT / name).exists():
                missing.append(f"{path.relative_to(ROOT)}: {name}")
    assert named >= 20 and missing == []


def test_the_link_check_covers_the_guide_and_the_dev_notes():
    from benchmarks import tables

    documents = {path.relative_to(ROOT).parts[:2] for path in tables.documents(ROOT)}
    assert ("docs", "guide") in documents and ("docs", "dev") in documents
