"""Ceilings on the generalisation protocol's objects (benchmarks/ceilings.py): the rows' arithmetic, and one
tiny end-to-end pass over a protocol run, resumed from its saved figures."""

from __future__ import annotations

import json
import math
import multiprocessing
import threading
import time

import pytest
import torch

import benchmarks.ceilings as ceilings
from benchmarks.ceilings import CHANNEL_GROUPS, ROWS, at_brightness, main, mean_rows, merge_with_saved, with_groups
from benchmarks.generalise import main as generalise
from matspray.asset import Asset
from matspray.config import build_config
from matspray.gaussians import Gaussians
from matspray.rundir import RUN_LOCK, RunDir, held_exclusively


def tiny_asset(materials: torch.Tensor) -> Asset:
    n = len(materials)
    gaussians = Gaussians(
        torch.zeros(n, 3),
        torch.zeros(n, 3),
        torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        torch.zeros(n),
        torch.zeros(n, 1, 3),
    )
    return Asset(gaussians, materials, torch.nn.functional.normalize(torch.ones(n, 3), dim=-1))


def test_with_groups_takes_only_the_named_channel_groups():
    asset = tiny_asset(torch.zeros(4, 5))
    source = torch.arange(20, dtype=torch.float32).reshape(4, 5) / 20
    rough = with_groups(asset, source, [CHANNEL_GROUPS["rough"]])
    assert torch.equal(rough.materials[:, 3], source[:, 3]) and not rough.materials[:, [0, 1, 2, 4]].any()
    every = with_groups(asset, source, CHANNEL_GROUPS.values())
    assert torch.equal(every.materials, source) and not asset.materials.any()  # the input asset is left as it was


def test_at_brightness_matches_the_reference_mean_base_colour_per_channel_and_keeps_the_rest():
    torch.manual_seed(0)
    materials, reference = torch.rand(50, 5) * 0.5, torch.rand(50, 5) * 0.5
    scaled = at_brightness(materials, reference)
    assert torch.allclose(scaled[:, :3].mean(0), reference[:, :3].mean(0), atol=1e-6)
    ratio = scaled[:, :3] / materials[:, :3]  # one scale per channel: the base colour's pattern is kept
    assert torch.allclose(ratio, ratio[:1].expand_as(ratio), atol=1e-5)
    assert torch.equal(scaled[:, 3:], materials[:, 3:])


def test_mean_rows_average_over_objects_and_drop_a_figure_some_object_lacks():
    def rows(relight, metal):
        return {row: {"relight": relight + i, "basecolor": 20.0, "metallic": metal} for i, row in enumerate(ROWS)}

    means = mean_rows([rows(20.0, 30.0), rows(22.0, math.inf)])
    assert means["proj-average"]["relight"] == pytest.approx(21.0) and means["lifted truth"][
        "relight"
    ] == pytest.approx(21.0 + ROWS.index("lifted truth"))
    assert "metallic" not in means["full"] and means["full"]["basecolor"] == 20.0  # inf (an exact map) is not averaged


def merge_one_model(path, model):  # a ceilings job of another process finishing its pass
    with held_exclusively(path):
        merge_with_saved(path, {model: [{"object": "dev-00", "rows": {row: {"relight": 20.0} for row in ROWS}}]})


def test_jobs_for_other_models_finishing_together_keep_each_others_figures(tmp_path):
    path = tmp_path / "ceilings-demo.json"
    merge_with_saved(path, {"paper": [{"object": "dev-00", "rows": {row: {"relight": 21.0} for row in ROWS}}]})
    context = multiprocessing.get_context("spawn")
    with held_exclusively(path):  # this process is mid-merge: the others wait for it
        others = [context.Process(target=merge_one_model, args=(path, model)) for model in ("harsh", "outliers")]
        for process in others:
            process.start()
        time.sleep(1.0)
        assert set(json.loads(path.read_text())) == {"paper"}  # neither wrote while the lock was held
        merge_with_saved(
            path, {"ground-truth": [{"object": "dev-00", "rows": {row: {"relight": 30.0} for row in ROWS}}]}
        )
    for process in others:
        process.join(timeout=60)
        assert process.exitcode == 0
    saved = json.loads(path.read_text())
    assert (
        set(saved) == {"paper", "harsh", "outliers", "ground-truth"}
        and saved["paper"][0]["rows"]["full"]["relight"] == 21.0
    )


def test_jobs_for_other_models_of_one_object_take_turns_on_its_ground_truth_run(tmp_path, monkeypatch):
    made = []  # (run folder, stage shared into it) and (run folder, predictor lifted in it), in order

    class RecordingPipeline:
        def __init__(self, data, out, config, **_):
            self.out, self.config = out, config

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

        def run_all(self, variants):
            made.append((self.out, self.config.predictor))
            return {variant: "asset" for variant in variants}

    monkeypatch.setattr(ceilings, "require_same_lift", lambda run, config: None)
    monkeypatch.setattr("matspray.rundir.share_stage", lambda source, target, stage: made.append((target, stage)))
    monkeypatch.setattr("matspray.pipeline.Pipeline", RecordingPipeline)
    truth_run = tmp_path / "runs" / "ground-truth"
    config = build_config("test")
    job = threading.Thread(
        target=ceilings.lift_truth, args=(tmp_path / "data", tmp_path / "runs" / "harsh", truth_run, config)
    )
    with RunDir(truth_run).hold():  # another job is lifting the truth of this object
        job.start()
        time.sleep(0.5)
        assert made == [] and [p.name for p in truth_run.iterdir()] == [RUN_LOCK]  # this one waits for it
    job.join(timeout=30)
    assert not job.is_alive() and made == [(truth_run, "geometry"), (truth_run, "ground-truth")]


@pytest.mark.slow
def test_ceilings_of_a_protocol_run(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    out = tmp_path / "g"
    args = ["--set", "dev", "--objects", "1", "--preset", "test", "--models", "paper", "--out", str(out)]
    assert main(args) == 2  # the protocol has not run yet
    assert (
        "run `python -m benchmarks.generalise --set dev --objects 1 --models paper --preset test"
        in capsys.readouterr().err
    )
    assert generalise(args + ["--variants", "full", "proj-average", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "error model `paper` (SIMULATED predictor), mean of 1 objects" in printed
    rows = json.loads((out / "ceilings-test.json").read_text())["paper"][0]["rows"]
    assert list(rows) == list(ROWS)
    protocol = json.loads((out / "results-default.json").read_text())["models"]["paper"]["objects"][0]["figures"]
    assert rows["proj-average"]["relight"] == pytest.approx(
        protocol["relight"]["proj-average"], abs=1e-6
    )  # the protocol's own scores
    assert rows["full"]["relight"] == pytest.approx(protocol["relight"]["full"], abs=1e-6)
    assert (
        rows["lifted truth"]["basecolor"] > rows["proj-average"]["basecolor"]
    )  # the true maps beat the simulated ones
    assert rows["oracle base only"]["roughness"] == pytest.approx(
        rows["proj-average"]["roughness"]
    )  # one channel group swapped
    true_light = out / "objects" / "dev-00-seed1000" / "runs" / "paper-true-light"
    assert (true_light / "asset" / "asset.ply").exists() and (true_light / "asset" / "envmap.exr").exists()
    assert rows["full, true light"]["relight"] != rows["full"]["relight"]  # refined again, under another light

    assert rows["lifted truth, PA brightness"]["roughness"] == pytest.approx(
        rows["lifted truth"]["roughness"]
    )  # only the base colour dimmed
    truth_run = out / "objects" / "dev-00-seed1000" / "runs" / "ground-truth"
    assert "lift" in json.loads((truth_run / "timings.json").read_text()) and "geometry" not in json.loads(
        (truth_run / "timings.json").read_text()
    )
    saved = (out / "objects" / "dev-00-seed1000" / "runs" / "paper" / "eval" / "ceilings.json").stat().st_mtime_ns
    saved_file = out / "ceilings-test.json"
    saved_file.write_text(
        json.dumps({**json.loads(saved_file.read_text()), "harsh": [{"object": "another", "rows": rows}]})
    )
    assert main(args) == 0  # a second pass reads the saved figures, and keeps the other model of an earlier pass
    assert capsys.readouterr().out == printed
    assert (
        set(json.loads(saved_file.read_text())) == {"paper", "harsh"}
        and "error model `harsh`" in (out / "ceilings-test.md").read_text()
    )
    assert (
        out / "objects" / "dev-00-seed1000" / "runs" / "paper" / "eval" / "ceilings.json"
    ).stat().st_mtime_ns == saved

    # a row missing from the saved figures (as after an upgrade that adds one) is computed alone; the others are reused
    saved = out / "objects" / "dev-00-seed1000" / "runs" / "paper" / "eval" / "ceilings.json"
    figures = json.loads(saved.read_text())
    figures["lifted truth"]["relight"] = -1.0  # marks a reused figure
    del figures["full, true light"]
    saved.write_text(json.dumps(figures))
    assert main(args) == 0
    again = json.loads((out / "ceilings-test.json").read_text())["paper"][0]["rows"]
    assert list(again) == list(ROWS) and again["lifted truth"]["relight"] == -1.0
    assert again["full, true light"]["relight"] == pytest.approx(
        rows["full, true light"]["relight"], abs=1e-6
    )  # the asset reused

    # a model kept from an earlier pass of a version with other rows is dropped, with a notice, not averaged half
    saved_file.write_text(
        json.dumps(
            {**json.loads(saved_file.read_text()), "harsh": [{"object": "another", "rows": {"full": {"relight": 1.0}}}]}
        )
    )
    capsys.readouterr()
    assert main(args) == 0
    assert "error model harsh in" in capsys.readouterr().out and set(json.loads(saved_file.read_text())) == {"paper"}
