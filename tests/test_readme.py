"""The README is for users: short, and free of history (no dates, commit hashes or issue numbers); the reference
pages carry no dates or commits either (history lives in docs/dev), and docs/dev/README.md indexes every log."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
# a commit: 7-40 hex digits alone in backticks, after "code"/"commit"/"at", or as a word of its own with a digit
HASH = re.compile(
    r"`[0-9a-f]{7,40}`|\b(?:code|commit|at)\s+[0-9a-f]{7,40}\b"
    r"|(?<![\w./-])(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w./-])"
)
ISSUE = re.compile(r"\bissues?\s?#?\d+|(?<![\w&])#\d+", re.I)


def history(text: str) -> list[str]:
    """The dates, commit hashes and issue numbers of a text."""
    return [m.group(0) for pattern in (DATE, HASH, ISSUE) for m in pattern.finditer(text)]


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("it took 4 min 19 s on 2026-11-29", ["2026-11-29"]),
        ("2D is the predictor's own maps (code 9e32ad8; before predicted normals)", ["code 9e32ad8"]),
        ("the merger in float32 (`bb9977a`)", ["`bb9977a`"]),
        ("at 477fd4b, alone on the 2 cores", ["at 477fd4b"]),
        ("the final main (b105512)", ["b105512"]),
        ("Issue 54 asks `full` to relight", ["Issue 54"]),
        ("the cache's `alexnet-owt-7be5be79.pth`, a 1e-3 rate, 1000000 views, deadbeefcafe", []),
    ],
)
def test_history_finds_dates_hashes_and_issues(text, found):
    assert history(text) == found


def test_the_readme_is_at_most_150_lines_without_history():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    assert history(text) == []
    assert not re.search(r"not yet run end to end|H200|five runs", text)


def test_the_readme_points_to_the_docs_index_not_into_the_logs():
    text = (ROOT / "README.md").read_text()
    assert "(docs/README.md)" in text
    assert len(re.findall(r"\]\(docs/dev/", text)) <= 2


def test_the_reference_pages_carry_no_dates_or_commits():
    found = {
        page.name: history(page.read_text())
        for page in sorted((ROOT / "docs").glob("*.md"))
        if DATE.search(page.read_text()) or HASH.search(page.read_text())
    }
    assert found == {}, "history belongs in docs/dev (docs/dev/history.md lists the code behind reference figures)"


def test_the_dev_index_lists_every_log():
    index = (ROOT / "docs" / "dev" / "README.md").read_text()
    listed = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    logs = {page.name for page in (ROOT / "docs" / "dev").glob("*.md")} - {"README.md"}
    assert logs <= listed, f"docs/dev/README.md does not list {sorted(logs - listed)}"
