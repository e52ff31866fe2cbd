"""Ceilings on the generalisation protocol's objects (benchmarks/ceilings.py): the rows' arithmetic, and one
tiny end-to-end pass over a protocol run, resumed from its saved figures."""

from __future__ import annotations

import json
import math
import multiprocessing
import threading
import time
from dataclasses import replace

import pytest
import torch

import benchmarks.ceilings as ceilings
from benchmarks.ceilings import (
    at_brightness,
    gbuffer_row_figures,
    main,
    merge_with_saved,
    shading_ceiling,
    summary_figures,
    with_groups,
    with_normals_of,
)
from benchmarks.ceilings_markdown import CHANNEL_GROUPS, GBUFFER_ROWS, ROWS, markdown, material_costs, mean_rows
from benchmarks.generalise import main as generalise
from matspray.errors import RunError
from matspray.gaussians import Gaussians
from matspray.method.asset import Asset
from matspray.method.config import build_config
from matspray.rundir import RUN_LOCK, RunDir, held_exclusively
from tests.scenes import ring_cameras, sky_map, sphere_of_disks

OLD_ROWS = [r for r in ROWS if r != "lifted truth, full's normals" and r not in GBUFFER_ROWS]  # older files


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


@pytest.fixture(scope="module")
def gbuffer_scene(tmp_path_factory):
    """One 32 px test view of the disk sphere (one: the metrics take the time): its truth (the sphere's own maps, the
    normals in `{view}_normal.exr` as `matspray synth` writes them, relit under two lights), the lights, and a
    "lifted truth" with materials blurred towards grey, tilted normals and a smaller outline (holes in its coverage
    of the true mask)."""
    from matspray.data import View, write_image
    from matspray.eval.run_eval import GroundTruth, unpremultiply
    from matspray.geometry.evaluate import true_normals
    from matspray.method.relight import render_gbuffer, render_relit
    from matspray.render.shade.envmap import EnvironmentMap

    folder = tmp_path_factory.mktemp("gbuffer-scene")
    gaussians, normals, materials = sphere_of_disks(n=300)
    true_asset = Asset(gaussians, materials, normals)
    gains = {"sky": 1.0, "dusk": 0.3}
    lights = {name: EnvironmentMap.from_tensor(sky_map() * g, learnable=False).prefilter() for name, g in gains.items()}
    camera = ring_cameras(1, 32)[0]
    view = View("r_000", torch.zeros(32, 32, 3), None, camera, folder / "r_000.png")
    with torch.no_grad():
        true = render_gbuffer(true_asset, camera)
    write_image(folder / "r_000_normal.exr", torch.nn.functional.normalize(true.normals, dim=-1))
    relit = {  # under brighter lights than ours: our renderer does not match the truth exactly (nor Mitsuba's)
        name: unpremultiply(*render_relit(true_asset, camera, EnvironmentMap.from_tensor(sky_map() * g * 1.2)))
        for name, g in gains.items()
    }
    truth = GroundTruth(true.alpha, true.base_color, true.roughness, true.metallic, relit, true_normals(view))
    shrunk = replace(gaussians, means=0.9 * gaussians.means)  # a smaller outline leaves the true one's rim uncovered
    tilted = torch.nn.functional.normalize(
        normals + 0.4 * torch.randn(len(normals), 3, generator=torch.Generator().manual_seed(1)), dim=-1
    )
    lifted = Asset(shrunk, 0.6 * materials + 0.2, tilted)
    return [view], [truth], lights, lifted


def asset_figures(asset, views, truths, lights) -> dict:  # how run_ceilings scores an asset's row
    from matspray.eval.run_eval import evaluate_asset

    return summary_figures(evaluate_asset(asset, views, truths, lights, None)["summary"])


def test_every_gbuffer_row_is_finite_and_differs_from_the_lifted_truth_where_it_swaps_something(gbuffer_scene):
    views, truths, lights, lifted = gbuffer_scene
    lifted_truth = asset_figures(lifted, views, truths, lights)
    rows = {row: gbuffer_row_figures(lifted, views, truths, lights, sources) for row, sources in GBUFFER_ROWS.items()}
    for row, figures in rows.items():
        assert all(math.isfinite(v) for v in figures.values()), row
    # the true maps would score themselves: that row has only its relighting, the others the lifted truth's materials
    assert set(rows["true maps, Gaussian normals"]) == {"relight"}
    assert rows["lifted truth, true normals"] | {"relight": 0.0} == lifted_truth | {"relight": 0.0}
    assert rows["lifted truth, true normals"]["relight"] > lifted_truth["relight"] + 1.0  # the tilted normals cost
    assert rows["true maps, Gaussian normals"]["relight"] > lifted_truth["relight"] + 1.0  # so do the blurred maps
    assert abs(rows["lifted truth, true alpha"]["relight"] - lifted_truth["relight"]) > 0.01  # and the holes


def test_true_maps_with_the_true_normals_are_the_shading_ceiling(gbuffer_scene):
    views, truths, lights, lifted = gbuffer_scene
    sources = list(GBUFFER_ROWS["true maps, Gaussian normals"])
    sources[1] = "true"  # the Gaussians' normals swapped for the true ones too: nothing of the asset is left
    reference = shading_ceiling(views, truths, lights)["relighting"]["psnr"]
    assert gbuffer_row_figures(lifted, views, truths, lights, tuple(sources))["relight"] == pytest.approx(
        reference, abs=1e-5
    )


def test_the_true_alpha_of_an_asset_whose_alpha_is_the_mask_is_the_lifted_truth(gbuffer_scene):
    from matspray.method.relight import render_gbuffer

    views, truths, lights, lifted = gbuffer_scene
    with torch.no_grad():  # the truth's mask made the asset's coverage: the row has nothing left to swap
        truths = [replace(t, mask=render_gbuffer(lifted, v.camera).alpha) for v, t in zip(views, truths)]
    swapped = gbuffer_row_figures(lifted, views, truths, lights, GBUFFER_ROWS["lifted truth, true alpha"])
    assert swapped == pytest.approx(asset_figures(lifted, views, truths, lights), abs=1e-9)


def test_normals_are_swapped_only_between_assets_on_the_same_gaussians(gbuffer_scene):
    views, truths, lights, lifted = gbuffer_scene
    donor = Asset(lifted.gaussians, torch.zeros_like(lifted.materials), -lifted.normals)
    swapped = with_normals_of(lifted, donor, "RUN/asset")
    assert torch.equal(swapped.normals, donor.normals) and torch.equal(swapped.materials, lifted.materials)
    assert all(math.isfinite(v) for v in asset_figures(swapped, views, truths, lights).values())
    with pytest.raises(RunError, match="RUN/asset holds other Gaussians than the lifted truth"):
        with_normals_of(lifted, tiny_asset(torch.zeros(4, 5)), "RUN/asset")


def test_the_markdown_splits_the_gap_from_the_lifted_truth_to_the_true_gbuffer():
    relight = {row: 20.0 + i for i, row in enumerate(ROWS)}
    relight |= {"lifted truth": 25.0, "true maps, Gaussian normals": 28.0, "lifted truth, true normals": 30.0}
    relight["true G-buffer"] = 33.0
    results = {"dr": [{"object": "dev-00", "rows": {row: {"relight": r} for row, r in relight.items()}}]}
    text = "\n".join(markdown("dev", "demo", results))
    assert "Where the 8.00 dB from the lifted truth to the true G-buffer go" in text
    assert "| lifted truth, true normals | 30.00 | 5.00 | 3.00 |" in text  # fixing the normals gains 5 dB, 3 are left
    assert "the Gaussians' normals alone cost 5.00 dB, the lift's material blur (+ alpha) alone 3.00 dB" in text
    assert "the difference (0.00 dB) is their interaction" in text  # 5 + 3 of the 8 dB: they add up here
    # a results file of an older version, without the rows: its tables as before, no decomposition
    old = {"dr": [{"object": "dev-00", "rows": {r: v for r, v in results["dr"][0]["rows"].items() if r in OLD_ROWS}}]}
    text = "\n".join(markdown("dev", "demo", old))
    assert "Where the" not in text and "| true G-buffer | 33.00 |" in text and "true normals" not in text


def test_the_markdown_says_what_each_of_fulls_materials_costs_it():
    relight = {row: 24.0 for row in ROWS}
    relight |= {"full, true base": 26.5, "full, true rough": 24.25, "full, true metal": 23.5}
    relight["full, truth's brightness"] = 25.0
    results = {"dr": [{"object": "dev-00", "rows": {row: {"relight": r} for row, r in relight.items()}}]}
    line = "lifted truth's materials in place of its own gains (dB): base 2.50, rough 0.25, metal -0.50, base "
    assert line + "brightness and tint 1.00" in "\n".join(markdown("dev", "demo", results))
    means = mean_rows([results["dr"][0]["rows"]])
    del means["full, true metal"]  # a results file of a version without the row
    assert material_costs(means) == []


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
            self.out, self.config, self.plan = out, config, None

        def resolved(self):
            return self.plan

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

        def run_all(self, variants):
            made.append((self.out, self.config.predictor))
            return {variant: "asset" for variant in variants}

    monkeypatch.setattr(ceilings, "require_same_lift", lambda run, config: None)
    monkeypatch.setattr("matspray.rundir.share_stage", lambda source, target, stage: made.append((target, stage)))
    monkeypatch.setattr("matspray.method.pipeline.Pipeline", RecordingPipeline)
    monkeypatch.setattr("matspray.method.plan.on_geometry", lambda plan, geometry: plan)
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
    split = ("lifted truth, full's normals", *GBUFFER_ROWS)  # the rows splitting lifted truth -> true G-buffer
    assert all(math.isfinite(rows[row]["relight"]) for row in split) and "Where the" in printed
    assert rows["lifted truth, full's normals"]["roughness"] == rows["lifted truth"]["roughness"]  # its materials
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
    swapped = rows["full, true rough"]  # full's base colour and metallic, the lifted truth's roughness
    assert swapped["roughness"] == pytest.approx(rows["lifted truth"]["roughness"])
    assert swapped["basecolor"] == pytest.approx(rows["full"]["basecolor"])
    assert swapped["metallic"] == pytest.approx(rows["full"]["metallic"])
    brightness = rows["full, truth's brightness"]  # only full's base colour rescaled
    assert brightness["roughness"] == pytest.approx(rows["full"]["roughness"])
    assert brightness["basecolor"] != pytest.approx(rows["full"]["basecolor"])
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

    # --rows computes and reports only the rows asked for (here none is missing: every one is read back)
    assert main([*args, "--rows", "proj-average", "lifted truth"]) == 0
    only = json.loads((out / "ceilings-test.json").read_text())["paper"][0]["rows"]
    assert list(only) == ["proj-average", "lifted truth"] and only["lifted truth"]["relight"] == -1.0

    # a model kept from an earlier pass of a version with other rows is dropped, with a notice, not averaged half
    saved_file.write_text(
        json.dumps(
            {**json.loads(saved_file.read_text()), "harsh": [{"object": "another", "rows": {"full": {"relight": 1.0}}}]}
        )
    )
    capsys.readouterr()
    assert main(args) == 0
    assert "error model harsh in" in capsys.readouterr().out and set(json.loads(saved_file.read_text())) == {"paper"}


@pytest.mark.slow
def test_a_configuration_that_trains_its_own_geometry_gets_its_own_lifted_truth(tmp_path, capsys):
    # generalise --geometry: each run trains its geometry (here on the simulated predictor's normals); ceilings
    # --configuration lifts the truth onto that run's Gaussians, not onto the default runs'
    pytest.importorskip("mitsuba")
    out = tmp_path / "g"
    common = ["--set", "dev", "--objects", "1", "--preset", "test", "--models", "paper", "--out", str(out)]
    argv = common + ["--variants", "full", "proj-average", "--no-progress", "--geometry", "predicted_normal_weight=0.5"]
    assert generalise(argv) == 0
    printed = capsys.readouterr().out
    runs = out / "objects" / "dev-00-seed1000" / "runs"
    (run,) = runs.glob("paper-matspray-*")
    assert "geometry shared" not in printed and "geometry" in json.loads((run / "timings.json").read_text())
    assert '"predicted_normal_weight": 0.5' in (run / "geometry" / "stage.json").read_text()
    report = json.loads(next(out.glob("results-*.json")).read_text())
    assert report["settings"]["geometry_overrides"] == {"predicted_normal_weight": 0.5}
    key = run.name[len("paper-") :]
    rows = ["proj-average", "lifted truth"]
    assert main(common + ["--configuration", key, "--rows", *rows]) == 0
    truth_run = runs / f"ground-truth-on-{run.name}"
    geometry = RunDir(run).stage_fingerprint("geometry")
    assert RunDir(truth_run).stage_fingerprint("geometry") == geometry  # the run's Gaussians, not trained again
    assert "geometry" not in json.loads((truth_run / "timings.json").read_text())
    figures = json.loads((out / f"ceilings-test-{key}.json").read_text())["paper"][0]["rows"]
    assert figures["proj-average"]["relight"] == pytest.approx(
        report["models"]["paper"]["objects"][0]["figures"]["relight"]["proj-average"], abs=1e-6
    )
    assert figures["lifted truth"]["basecolor"] > figures["proj-average"]["basecolor"]
    with pytest.raises(SystemExit) as refused:
        main(common + ["--configuration", key, "--rows", "full, true light"])
    assert refused.value.code == 2 and "refine the default runs only" in capsys.readouterr().err
    # a configuration with more than those geometry overrides starts from that configuration's geometry and lift
    assert generalise(argv + ["--refine", "iterations=4", "light_warmup=2"]) == 0
    assert "starts from paper's materials2d, geometry, lift" in capsys.readouterr().out
    (other,) = set(runs.glob("paper-matspray-*")) - {run}
    assert not {"materials2d", "geometry", "lift"} & set(json.loads((other / "timings.json").read_text()))


def test_the_markdown_of_rows_without_proj_average_leaves_the_gap_to_it_empty():
    results = {
        "paper": [{"object": "dev-b-00", "rows": {"full": {"relight": 26.0}, "lifted truth": {"relight": 28.0}}}]
    }
    text = "\n".join(markdown("eval", "demo", results))  # `--rows full "lifted truth"`: no proj-average to compare with
    assert "| full | 26.00 | — |" in text and "| lifted truth | 28.00 | — |" in text
    assert "- full - proj-average" not in text


def test_each_geometry_of_an_objects_runs_gets_its_own_lifted_truth(tmp_path):
    from matspray.rundir import STAGE_RECORD

    def run_with_geometry(name, fingerprint):
        run = tmp_path / name
        (run / "geometry").mkdir(parents=True)
        (run / "geometry" / STAGE_RECORD).write_text(json.dumps({"fingerprint": fingerprint}))
        return run

    paper, harsh = run_with_geometry("paper", "a"), run_with_geometry("harsh", "a")
    outliers = run_with_geometry("outliers", "b")  # trained on other predicted normals
    # nothing lifted yet: the pass's first run claims ground-truth, the runs of another geometry get their own
    assert ceilings.truth_run_name(paper, paper, None) == "ground-truth"
    assert ceilings.truth_run_name(harsh, paper, None) == "ground-truth"  # one geometry, one lifted truth
    assert ceilings.truth_run_name(outliers, paper, None) == "ground-truth-on-outliers"
    # ground-truth already holds paper's geometry: a later pass of outliers alone does not claim it
    run_with_geometry("ground-truth", "a")
    assert ceilings.truth_run_name(outliers, outliers, None) == "ground-truth-on-outliers"
    assert ceilings.truth_run_name(harsh, outliers, None) == "ground-truth"
    keyed = run_with_geometry("paper-matspray-1234", "a")  # another configuration: always its own
    assert ceilings.truth_run_name(keyed, keyed, "matspray-1234") == "ground-truth-on-paper-matspray-1234"
