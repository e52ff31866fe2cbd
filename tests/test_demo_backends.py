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
