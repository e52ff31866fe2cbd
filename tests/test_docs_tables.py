"""The README's and docs' generated tables agree with the result files in docs/results/, and every relative link
in them points to a file that exists."""

import json
import re
import shutil
from pathlib import Path
from urllib.parse import unquote

from benchmarks import tables

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def copy_docs(tmp_path: Path) -> Path:
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    for path in (ROOT / "docs").rglob("*.md"):  # docs/, docs/guide/, docs/dev/
        target = tmp_path / path.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    shutil.copytree(ROOT / "docs" / "results", tmp_path / "docs" / "results")
    return tmp_path


def test_generated_tables_match_the_results_files():
    assert tables.differing(ROOT) == [], "run `python -m benchmarks.tables` and commit the result"


def test_every_table_has_its_results_and_every_results_file_a_table():
    used = set()
    for name, (_, files) in tables.TABLES.items():
        used.update(files)
        for file in files:
            assert (ROOT / tables.RESULTS / file).exists(), f"table {name} reads docs/results/{file}, which is missing"
    on_disk = {p.name for p in (ROOT / tables.RESULTS).glob("*.json")}
    assert on_disk <= used, f"results files no table reads: {sorted(on_disk - used)}"
    text = "\n".join(p.read_text() for p in tables.documents(ROOT))
    placed = {m.group(2) for m in tables.MARKER.finditer(text)}
    assert placed == set(tables.TABLES), f"tables defined but not placed: {sorted(set(tables.TABLES) - placed)}"


def test_a_changed_number_in_a_results_file_fails_the_check(tmp_path, capsys):
    root = copy_docs(tmp_path)
    assert tables.main(["--check", "--root", str(root)]) == 0
    path = root / "docs" / "results" / tables.EVAL_NORMALS
    report = json.loads(path.read_text())
    report["models"]["harsh"]["summary"]["relight"]["full"] += 0.5  # dev-b's means and no more
    changed = report["models"]["harsh"]["summary"]["relight"]["full"]
    path.write_text(json.dumps(report))
    assert tables.main(["--check", "--root", str(root)]) == 1
    printed = capsys.readouterr().out
    assert "benchmarks.md: table dev-b-headline" in printed
    assert "normals-eval" in printed  # the other table with the mean row
    assert "real-captures" not in printed and "no-prior-eval" not in printed and "generalise-eval" not in printed
    assert tables.main(["--root", str(root)]) == 0  # regenerate; then the check passes
    assert tables.main(["--check", "--root", str(root)]) == 0
    assert f"| `harsh` | {changed:.2f} |" in (root / "docs" / "benchmarks.md").read_text()


def test_an_edited_table_fails_the_check(tmp_path, capsys):
    root = copy_docs(tmp_path)
    page = root / "docs" / "benchmarks.md"
    text = page.read_text()
    edited = re.sub(
        r"\| skull \| whole \| (\d+) \|", lambda m: f"| skull | whole | {int(m.group(1)) + 1} |", text, count=1
    )
    assert edited != text  # the skull's held-out views, one more
    page.write_text(edited)
    assert tables.main(["--check", "--root", str(root)]) == 1
    assert "benchmarks.md: table captures-headline" in capsys.readouterr().out


def test_relative_links_point_to_existing_files():
    broken = []
    for doc in tables.documents(ROOT):
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)  # not links inside code blocks
        for target in LINK.findall(text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # web addresses, mail, anchors in the same file
            path = (doc.parent / unquote(target.split("#")[0])).resolve()
            if not path.exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert broken == []


def test_readme_is_short_and_cites_no_path_outside_the_repository():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    assert "../shared" not in text
    assert not re.search(r"\bissues? \d+", text, re.I)


def test_the_cli_reference_does_not_depend_on_this_machine(monkeypatch, tmp_path):
    # CI checks the tables in another folder and environment: no path or variable of this one may reach them
    before = tables.table_cli(ROOT / tables.RESULTS)
    monkeypatch.setenv("MATSPRAY_LPIPS_WEIGHTS", str(tmp_path / "elsewhere.npz"))
    monkeypatch.setenv("HOME", str(tmp_path))
    after = tables.table_cli(ROOT / tables.RESULTS)
    assert after == before
    assert str(ROOT.parent) not in before and str(tmp_path) not in after
