"""Every measured figure that README.md, docs/benchmarks.md and docs/method.md quote comes from a table generated from
docs/results/ (`python -m benchmarks.tables`); a figure typed by hand there fails, and `--check` names it."""

import shutil
from pathlib import Path

import pytest

from benchmarks import tables
from benchmarks.tables_figures import hand_typed, hand_typed_figures

ROOT = Path(__file__).resolve().parents[1]

# sentences of the README and docs/benchmarks.md before their figures moved to docs/dev, and what each holds
OLD_SENTENCES = [
    ("it took 4 min 19 s on 2026-11-29: the demo itself 210 s", ["4 min", "19 s", "210 s"]),
    ("83 s on one H200 with `MAX_JOBS=12`", ["83 s"]),
    ("Gaussian Splatting 136\nsteps/s, lifting 0.56 s per view", ["136\nsteps/s", "0.56 s"]),
    ("`seen-input` (the merger reading which views saw a Gaussian): -0.03 dB on average", ["-0.03 dB"]),
    ("focal length within 2.1% of the true one", ["2.1%"]),
    ("two threads were 1.5x faster than one", ["1.5x"]),
    ("median rates geometry 1.03e-5, lift 1.81e-5", ["1.03e-5", "1.81e-5"]),
    ("renders min 64.6 / mean 67.6 dB, base colour 74.9 / 76.8", ["64.6", "67.6 dB", "74.9", "76.8"]),
    ("(81 % of the Gaussians on it)", ["81 %"]),
    ("Shadows pay (the demo's object: +2.7 dB relighting)", ["+2.7 dB"]),
]

# numbers that are not measurements: sizes, counts, settings, versions, licences, seeds, code
NOT_FIGURES = [
    "the paper's object and settings (512 px, 100 views), 16 x 16 rays per pixel, 4x4 rays",
    "six objects, 128 px, 40 views, relit under two held-out lights; seeds 2000 + i",
    "Python >= 3.10, gsplat 1.5, glTF 2.0, CC BY 4.0, six lights (1.5 MB)",
    "`--set lift.min_support=0.5 refine.normal_lr=0`, `torch==2.13.0`, eq. 1-3, l.209",
    "```bash\nmatspray run --set refine.light_tv_weight=0.0003\n```",
    "code 9e32ad8 (a hash, not a rate)",
    "<!-- table: headline -->\n| `paper` | 26.80 | 24.10 dB | 81 % | 1.5x |\n<!-- /table -->",
]


@pytest.mark.parametrize(("text", "figures"), OLD_SENTENCES)
def test_the_detector_finds_each_kind_of_measured_figure(text, figures):
    assert [figure for _, figure in hand_typed(text)] == sorted(figures, key=text.index)


@pytest.mark.parametrize("text", NOT_FIGURES)
def test_sizes_counts_settings_versions_and_generated_tables_are_not_figures(text):
    assert hand_typed(text) == []


def test_line_numbers_count_the_generated_tables_lines():
    text = "intro\n<!-- table: x -->\n| 1.5 dB |\n<!-- /table -->\nthen 3 s\n"
    assert hand_typed(text) == [(5, "3 s")]


def test_readme_benchmarks_and_method_quote_no_figure_typed_by_hand():
    assert hand_typed_figures(ROOT) == [], "generate each figure from docs/results, or move it to a log in docs/dev"


def test_check_fails_on_a_figure_typed_by_hand(tmp_path, capsys):
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    for path in (ROOT / "docs").rglob("*.md"):  # every page with a generated table
        target = tmp_path / path.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    shutil.copytree(ROOT / "docs" / "results", tmp_path / "docs" / "results")
    assert tables.main(["--check", "--root", str(tmp_path)]) == 0
    readme = tmp_path / "README.md"
    readme.write_text(readme.read_text().replace("## Quickstart", "## Quickstart\n\nThe demo takes 4 min 19 s.", 1))
    assert tables.main(["--check", "--root", str(tmp_path)]) == 1
    printed = capsys.readouterr().out
    assert "a figure typed by hand outside a generated table: README.md:" in printed
    assert "4 min" in printed and "19 s" in printed
