"""benchmarks.demo_backends: the comparison of two demo runs' evaluations."""

import json

from benchmarks.demo_backends import compare, main


def fake_run(folder, relight, metallic):
    (folder / "eval").mkdir(parents=True)
    summary = {"relighting": {"psnr": relight}, "metallic": {"psnr": metallic}, "relighting_union": {"psnr": 1.0}}
    variants = {"full": {"summary": summary}, "no-prior": {"summary": summary}}
    (folder / "eval" / "metrics.json").write_text(json.dumps({"variants": variants}))
    return folder


def test_two_runs_are_compared_figure_by_figure_and_the_tolerance_decides(tmp_path, capsys):
    torch_run = fake_run(tmp_path / "torch", 25.0, 24.0)
    numba_run = fake_run(tmp_path / "numba", 25.05, 23.8)
    result = compare(torch_run, numba_run)
    assert [(r["variant"], r["row"]) for r in result["rows"]] == [
        ("full", "relighting"), ("full", "metallic"), ("no-prior", "relighting"), ("no-prior", "metallic")
    ]  # fmt: skip
    assert abs(result["largest"] - 0.2) < 1e-9
    args = ["--runs", str(torch_run), str(numba_run), "--results-dir", str(tmp_path / "results")]
    assert main(args + ["--tolerance", "0.1"]) == 1
    assert "NOT within 0.1 dB" in capsys.readouterr().out
    assert main(args + ["--tolerance", "0.25"]) == 0
    written = json.loads((tmp_path / "results" / "demo-backends.json").read_text())
    assert written["tolerance"] == 0.25 and len(written["rows"]) == 4


def test_the_refinement_seeds_spread_is_shown_beside_each_figure(tmp_path, capsys):
    runs = [fake_run(tmp_path / name, relight, metal) for name, relight, metal in (
        ("torch", 25.0, 24.0), ("numba", 25.05, 23.8), ("torch-seed1", 25.3, 24.1), ("numba-seed1", 24.95, 23.8)
    )]  # fmt: skip
    result = compare(runs[0], runs[1], (runs[2], runs[3]))
    spread = {(r["variant"], r["row"]): r["seed_spread"] for r in result["rows"]}
    assert abs(spread["full", "relighting"]["torch"] - 0.3) < 1e-9
    assert abs(spread["full", "relighting"]["numba"] + 0.1) < 1e-9 and abs(spread["full", "metallic"]["numba"]) < 1e-9
    args = ["--runs", *map(str, runs[:2]), "--seed-runs", *map(str, runs[2:]), "--results-dir", str(tmp_path)]
    assert main(args + ["--tolerance", "0.25"]) == 0
    assert "largest change from the refinement seed alone: 0.30 dB" in capsys.readouterr().out
    assert json.loads((tmp_path / "demo-backends.json").read_text())["seed_runs"] == [str(runs[2]), str(runs[3])]


def test_seed_runs_without_runs_are_refused(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["--seed-runs", "a", "b"])
    assert "--seed-runs compares against --runs" in capsys.readouterr().err
