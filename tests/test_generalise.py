"""The generalisation protocol (benchmarks/generalise.py): object sets, settings overrides, geometry
shared between error models, the tables' means and wins, and one tiny end-to-end run."""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, replace
from pathlib import Path

import pytest

from benchmarks.generalise import (
    geometry_run,
    main,
    parse_args,
    predictor_spec,
    refine_overrides,
    with_overrides,
)
from benchmarks.generalise_sets import MAX_OBJECTS, SET_SEEDS, object_set, with_training_light
from benchmarks.generalise_tables import model_summary, model_table
from matspray.data.images import read_image
from matspray.errors import ConfigError
from matspray.geometry.config import GeometryConfig
from matspray.method.refine.loop import RefineConfig
from matspray.render.shade.lights import BUILTINS
from matspray.rundir import newer_than_stages, share_stage

HDRIS = ["city", "forest", "interior", "studio", "sunrise", "sunset"]
# one object of the dev set at the test preset, error model `paper`: the end-to-end tests add their own flags
ONE_OBJECT = ["--set", "dev", "--objects", "1", "--preset", "test", "--models", "paper"]


def test_object_sets_have_disjoint_seeds_and_draw_their_lights():
    dev, evaluation = object_set("dev", 50, HDRIS), object_set("dev-b", 50, HDRIS)
    assert {o.seed for o in dev}.isdisjoint({o.seed for o in evaluation})
    assert [o.seed for o in dev] == list(range(SET_SEEDS["dev"], SET_SEEDS["dev"] + 50))
    assert object_set("dev", 3, HDRIS) == dev[:3]  # the first K objects of a set do not depend on K
    for o in dev + evaluation:
        assert o.env in HDRIS  # trained under an HDRI
        assert len(set(o.relight_envs)) == 2 and o.env not in o.relight_envs
        assert set(o.relight_envs) <= set(HDRIS) | set(BUILTINS)
    assert len({o.env for o in dev}) > 3 and any(set(o.relight_envs) & set(BUILTINS) for o in dev)  # the draws vary
    assert all(o.env in BUILTINS for o in object_set("dev", 5, []))  # without the shared HDRIs
    with pytest.raises(ConfigError, match=rf"--objects must be in \[1, {MAX_OBJECTS}\] for the set dev, got 0"):
        object_set("dev", 0, HDRIS)
    with pytest.raises(ConfigError, match="unknown object set 'test'"):
        object_set("test", 1, HDRIS)
    with pytest.raises(ConfigError, match="'eval' is now named 'dev-b'.*the evaluation set is real-eval"):
        object_set("eval", 1, HDRIS)


def test_object_sets_keep_their_lights_after_the_hdris_were_renamed():
    """studio-small and venice-sunset were named studio and sunset (names that gave the built-ins): every object of
    both sets keeps the lights it was measured under."""
    from matspray.render.shade.lights import hdri_files

    for which in ("dev", "dev-b"):
        assert object_set(which, 30, sorted(hdri_files())) == object_set(which, 30, HDRIS)


def test_a_training_light_for_every_object_names_their_folders_and_never_a_held_out_light():
    objects = object_set("real-dev", None, ["city", "studio-small"])
    lit = with_training_light(objects, "sunset")
    assert [o.env for o in lit] == ["sunset"] * 3 and [o.relight_envs for o in lit] == [o.relight_envs for o in objects]
    assert [o.name for o in lit] == [f"{o.name}-train-sunset" for o in objects]
    assert with_training_light(objects, None) == objects
    with pytest.raises(ConfigError, match="relit under it; choose another light"):
        with_training_light(objects, objects[0].relight_envs[0])


def test_predictor_specs():
    assert [predictor_spec(m) for m in ("paper", "harsh", "outliers", "ground-truth")] == [
        "simulated:paper",
        "simulated:harsh",
        "simulated:outliers",
        "ground-truth",
    ]
    with pytest.raises(ConfigError, match="unknown error model 'mild'"):
        predictor_spec("mild")


def test_refine_overrides_are_typed_and_checked():
    config = with_overrides(
        RefineConfig(),
        ["iterations=7", "photo_weight=0.5", "merger.softmax=false", "merger.hidden=32", "basecolor_loss=l1"],
    )
    assert (
        config.iterations,
        config.photo_weight,
        config.merger.softmax,
        config.merger.hidden,
        config.basecolor_loss,
    ) == (7, 0.5, False, 32, "l1")
    assert refine_overrides(RefineConfig(), ["iterations=7"]) == {"iterations": 7}
    assert refine_overrides(RefineConfig(), []) == {}
    with pytest.raises(ConfigError, match=r"--refine iterations=many: expected an integer"):
        with_overrides(RefineConfig(), ["iterations=many"])
    with pytest.raises(ConfigError, match=r"--refine speed=3: expected KEY=VALUE with KEY one of"):
        with_overrides(RefineConfig(), ["speed=3"])
    with pytest.raises(
        ConfigError,
        match=r"--refine merger.width=3: expected KEY=VALUE with KEY one of merger.frequencies, merger.hidden",
    ):
        with_overrides(RefineConfig(), ["merger.width=3"])
    with pytest.raises(ConfigError, match="set the fields of 'merger' as merger.KEY=VALUE"):
        with_overrides(RefineConfig(), ["merger=3"])
    with pytest.raises(ConfigError, match=r"--refine merger.softmax=maybe: expected true or false"):
        with_overrides(RefineConfig(), ["merger.softmax=maybe"])
    with pytest.raises(ConfigError, match="unknown loss 'l7'"):
        with_overrides(RefineConfig(), ["basecolor_loss=l7"])


def test_share_stage_links_a_finished_stage_once(tmp_path):
    source, target = tmp_path / "a", tmp_path / "b"
    (source / "geometry" / "renders").mkdir(parents=True)
    (source / "geometry" / "stage.json").write_text('{"fingerprint": "x"}')
    (source / "geometry" / "renders" / "r.png").write_bytes(b"png")
    os.utime(source / "geometry" / "stage.json", (1e9, 1e9))  # finished long ago
    (target / "eval").mkdir(parents=True)
    (target / "eval" / "metrics.json").write_text(
        "{}"
    )  # a figure the target derived before the share (and after the source)
    os.utime(target / "eval" / "metrics.json", (1.5e9, 1.5e9))
    assert share_stage(source, target, "geometry")
    assert os.path.samefile(source / "geometry" / "renders" / "r.png", target / "geometry" / "renders" / "r.png")
    assert (target / "geometry" / "stage.json").read_text() == '{"fingerprint": "x"}'
    assert (source / "geometry" / "stage.json").stat().st_mtime == 1e9  # the source is left as it was
    assert not newer_than_stages(target / "eval" / "metrics.json", target)  # the figure is older than the shared stage
    assert not share_stage(source, target, "geometry")  # already there
    assert not share_stage(tmp_path / "none", tmp_path / "c", "geometry") and not (tmp_path / "c").exists()


def test_geometry_run_is_one_with_finished_geometry(tmp_path):
    assert geometry_run(tmp_path, "harsh") == tmp_path / "harsh"  # nothing trained yet: the first model's
    (tmp_path / "paper" / "geometry").mkdir(parents=True)
    assert geometry_run(tmp_path, "harsh") == tmp_path / "harsh"  # unfinished geometry does not count
    (tmp_path / "paper" / "geometry" / "stage.json").write_text("{}")
    assert geometry_run(tmp_path, "harsh") == tmp_path / "paper"


def test_a_geometry_trained_with_other_settings_is_not_shared(tmp_path):
    """Each model's run trains on its own predicted normals by default; a pass with them off must not take one of
    those geometries (it would share it, then find its settings differ and stop on its checkpoint)."""
    off = GeometryConfig(predicted_normal_weight=0.0)
    on = replace(off, predicted_normal_weight=1.0)
    for name, settings in (("paper", on), ("harsh", off)):
        (tmp_path / name / "geometry").mkdir(parents=True)
        record = {"fingerprint": name, "settings": asdict(settings.for_scene(masked=True))}
        (tmp_path / name / "geometry" / "stage.json").write_text(json.dumps(record))
    assert geometry_run(tmp_path, "outliers", off) == tmp_path / "harsh"
    assert geometry_run(tmp_path, "outliers", on) == tmp_path / "paper"
    assert geometry_run(tmp_path, "outliers", replace(off, iterations=10)) == tmp_path / "outliers"  # none has those
    # a record from before a setting existed holds the value that leaves it out of the identity
    old = asdict(off.for_scene(masked=True))
    del old["material_edge_threshold"]
    (tmp_path / "harsh" / "geometry" / "stage.json").write_text(json.dumps({"fingerprint": "h", "settings": old}))
    assert geometry_run(tmp_path, "outliers", off) == tmp_path / "harsh"


def fake_run(full, average, no_softmax, base3, base2, metal3, metal2, no_prior=None, base_no_prior=None):
    """The parts of eval/metrics.json the protocol reads."""

    def entry(psnr):
        return {"psnr": psnr, "ssim": 0.9, "lpips": None}

    variants = {
        v: {"summary": {"relighting": entry(p)}}
        for v, p in (("full", full), ("proj-average", average), ("no-softmax", no_softmax), ("no-prior", no_prior))
        if p is not None
    }
    summary = variants["full"]["summary"]
    summary.update(
        basecolor=entry(base3),
        roughness=entry(20.0),
        metallic=dict(entry(metal3), psnr_infinite=int(math.isinf(metal3)), objects=1),
    )
    predictions = {"basecolor": entry(base2), "roughness": entry(21.0), "metallic": entry(metal2)}
    table1 = {
        "Ours": {k: summary[k] for k in ("basecolor", "roughness", "metallic")},
        "2D predictions": {
            **predictions,
            "metallic": dict(entry(metal2), psnr_infinite=int(math.isinf(metal2)), objects=1),
        },
    }
    if no_prior is not None:
        baseline = variants["no-prior"]["summary"]
        baseline.update(
            basecolor=entry(base_no_prior),
            roughness=entry(15.0),
            metallic=dict(entry(10.0), psnr_infinite=0, objects=1),
        )
        table1["No prior (R3DGS-like)"] = dict(baseline)
    return {
        "variants": variants,
        "predictions_2d": predictions,
        "table1": table1,
        "table2": {"Full": entry(full), "Proj. Average": entry(average)},
        "softmax": {"Full": entry(full), "Without Softmax": entry(no_softmax)},
        "timings": {},
    }


def test_means_and_wins_over_objects():
    from benchmarks.generalise_tables import object_figures

    runs = [
        fake_run(25.0, 24.0, 25.5, 22.0, 23.0, math.inf, 18.0, no_prior=23.0, base_no_prior=18.0),
        fake_run(26.0, 26.5, 25.0, 24.0, 23.0, 20.0, 19.0, no_prior=26.5, base_no_prior=19.0),
        fake_run(27.0, 26.0, 26.0, 21.0, 21.0, 22.0, math.inf, no_prior=24.5, base_no_prior=22.0),
    ]
    summary = model_summary([{"metrics": m, "figures": object_figures(m)} for m in runs])
    assert summary["relight"] == pytest.approx(
        {"full": 26.0, "proj-average": 25.5, "no-softmax": 25.5, "no-prior": 24.666666666666668}
    )
    assert summary["materials_no_prior"]["basecolor"]["psnr"] == pytest.approx(59.0 / 3)
    assert summary["materials_3d"]["basecolor"]["psnr"] == pytest.approx(67.0 / 3)
    assert summary["materials_3d"]["metallic"]["psnr"] == pytest.approx(
        21.0
    )  # the paper's rule: the infinite object left out
    assert summary["materials_3d"]["metallic"]["psnr_infinite"] == 1
    wins = {k: (w["wins"], w["of"]) for k, w in summary["wins"].items()}
    assert wins == {
        "full > proj-average": (2, 3),
        "full > no-softmax": (2, 3),
        "full > no-prior": (2, 3),
        "full > no-prior basecolor": (2, 3),
        "3D > 2D basecolor": (1, 3),
        "3D > 2D roughness": (0, 3),
        "3D > 2D metallic": (2, 3),
    }
    table = "\n".join(
        model_table(
            "paper",
            [
                {
                    "object": {"name": f"o{i}", "env": "e", "relight_envs": ["a"]},
                    "figures": object_figures(m),
                    "seconds": 1.0,
                }
                for i, m in enumerate(runs)
            ],
            summary,
            ["full", "no-prior"],
        )
    )
    assert "| relight no-prior |" in table and "| no-prior base |" in table and "| 24.67 |" in table


def test_the_scale_aligned_figures_have_their_own_table():
    """The TensoIR / IRGS convention (a per-channel scale fitted to the truth) beside the unaligned figures: means over
    the objects where every object has them, and no aligned table where the evaluation made none."""
    from benchmarks.generalise_tables import object_figures

    runs = [fake_run(25.0, 24.0, 25.5, 22.0, 23.0, 20.0, 18.0), fake_run(26.0, 26.5, 25.0, 24.0, 23.0, 20.0, 19.0)]
    for run, shift in zip(runs, (1.0, 3.0)):
        for name, variant in run["variants"].items():
            relit = variant["summary"]["relighting"]["psnr"]
            variant["summary"]["relighting_aligned"] = {"psnr": relit + shift, "ssim": 0.9, "lpips": None}
            variant["summary"]["basecolor_aligned"] = {"psnr": 20.0 + shift, "ssim": 0.9, "lpips": None}
    per_object = [
        {"object": {"name": f"o{i}", "env": "e", "relight_envs": ["a"]}, "figures": object_figures(m), "seconds": 1.0}
        for i, m in enumerate(runs)
    ]
    summary = model_summary([{"metrics": m, "figures": o["figures"]} for m, o in zip(runs, per_object)])
    assert summary["relight_aligned"] == pytest.approx({"full": 27.5, "proj-average": 27.25, "no-softmax": 27.25})
    assert summary["basecolor_aligned"]["full"] == pytest.approx(22.0)
    table = "\n".join(model_table("paper", per_object, summary, ["full", "proj-average"]))
    assert "unaligned PSNR" in table and "TensoIR / IRGS" in table
    assert "| **mean of 2** | 27.50 | 27.25 | 22.00 | 22.00 |" in table
    plain = [fake_run(25.0, 24.0, 25.5, 22.0, 23.0, 20.0, 18.0)]  # an evaluation without aligned rows
    figures = [
        {
            "object": {"name": "o", "env": "e", "relight_envs": ["a"]},
            "figures": object_figures(plain[0]),
            "seconds": 1.0,
        }
    ]
    summary = model_summary([{"metrics": plain[0], "figures": figures[0]["figures"]}])
    assert summary["relight_aligned"] == {} and "TensoIR" not in "\n".join(
        model_table("paper", figures, summary, ["full"])
    )


@pytest.mark.slow
def test_start_splits_a_pass_over_jobs(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    out = tmp_path / "g"
    second = [*ONE_OBJECT, "--start", "1"]
    assert main([*second, "--geometry-only", "--out", str(out), "--no-progress"]) == 0
    assert [p.name for p in (out / "objects").iterdir()] == ["dev-01-seed1001"]  # the set's second object only
    assert (out / "objects" / "dev-01-seed1001" / "runs" / "paper" / "geometry" / "stage.json").exists()
    part = ["--variants", "proj-average", "--tag", "part", "--out", str(out), "--no-progress"]
    assert main([*second, *part]) == 0
    report = json.loads((out / "results-part-from1.json").read_text())  # a part of a pass keeps its own files
    assert report["settings"]["start"] == 1 and [o["object"]["name"] for o in report["models"]["paper"]["objects"]] == [
        "dev-01-seed1001"
    ]
    timing = report["timing"][0]  # the model's own geometry (trained by the first call) is in the object's total
    assert timing["geometry"] > 0 and timing["total"] == pytest.approx(
        timing["synth"] + timing["geometry"] + sum(timing["models"].values())
    )
    for bad in (["--start", "-1"], ["--objects", "0", "--start", "2"]):
        with pytest.raises(SystemExit):
            main(["--set", "dev", *bad, "--out", str(out)])
        assert "--objects must be >= 1 and --start >= 0" in capsys.readouterr().err


def test_protocol_end_to_end_shares_geometry(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    out = tmp_path / "g"
    argv = [
        "--set",
        "dev",
        "--objects",
        "1",
        "--preset",
        "test",
        "--models",
        "paper",
        "ground-truth",
        "--variants",
        "full",
        "proj-average",
        "--method",
        "paper",
        "--refine",
        "iterations=4",
        "light_warmup=2",
        "--geometry",
        "predicted_normal_weight=0",  # a geometry that follows no model's normals is shared by the models
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    runs = out / "objects" / "dev-00-seed1000" / "runs"
    paper_run = next(runs.glob("paper-paper-*"))  # a configuration other than the default has run folders of its own
    truth_run = runs / paper_run.name.replace("paper-paper-", "ground-truth-paper-")
    assert f"geometry shared from {paper_run.name}" in printed
    assert "error model `paper` (SIMULATED predictor; unaligned PSNR)" in printed
    assert "error model `ground-truth`" in printed
    record = [json.loads((run / "geometry" / "stage.json").read_text()) for run in (paper_run, truth_run)]
    assert record[0] == record[1]  # one geometry, reused by the second model's pipeline
    assert "geometry" not in json.loads((truth_run / "timings.json").read_text())  # not trained again
    tag = next(out.glob("results-*.json")).stem[len("results-") :]
    report = json.loads((out / f"results-{tag}.json").read_text())
    assert report["settings"]["refine_overrides"] == {"iterations": 4, "light_warmup": 2} and tag.startswith("paper-")
    assert report["settings"]["method"] == "paper" and "method: paper" in (paper_run / "config.yaml").read_text()
    assert "seed: 1000" in (paper_run / "config.yaml").read_text()  # the predictor draws from the object's seed
    timing = report["timing"][0]  # geometry once, in its own column; the models' seconds without it
    assert timing["geometry"] > 0 and timing["total"] == pytest.approx(
        timing["synth"] + timing["geometry"] + sum(timing["models"].values())
    )
    truth = report["models"]["ground-truth"]["objects"][0]["figures"]
    assert math.isinf(truth["materials_2d"]["basecolor"])  # the sanity row: 2D maps are the truth
    paper = report["models"]["paper"]["objects"][0]["figures"]
    assert paper["materials_2d"]["basecolor"] < 40 and set(paper["relight"]) == {"full", "proj-average"}
    # the benchmark runs score the scale-aligned rows too (the fitted scale may cost a little where none is needed)
    assert paper["relight_aligned"]["full"] >= paper["relight"]["full"] - 0.5
    assert json.loads((paper_run / "materials2d" / "predictor.json").read_text())["error_model"] == "paper"
    assert (out / f"tables-{tag}-paper.md").exists() and (out / f"results-{tag}.md").exists()
    wins_line = next(line for line in (out / f"results-{tag}.md").read_text().splitlines() if line.startswith("wins:"))
    assert "full > proj-average" in wins_line and "no-softmax" not in wins_line  # a variant not run has no count
    assert main(["--compare", "--out", str(out)]) == 0  # the table of choices, from the saved results
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {tag} |")]
    assert [row.split(" | ")[3] for row in rows] == [
        "paper",
        "ground-truth",
    ] and "iterations=4, light_warmup=2" in rows[0]
    assert rows[1].split(" | ")[-3:] == ["-inf", "-inf", "-inf |"]  # the 3D materials never reach the exact 2D truth
    assert main(["--compare", "--out", str(tmp_path / "nothing")]) == 2
    assert "no results-*.json to compare" in capsys.readouterr().err
    assert main(argv[:-3] + ["--refine", "iterations=x", "--out", str(out)]) == 2
    assert "--refine iterations=x: expected an integer" in capsys.readouterr().err
    # a second pass reuses both finished runs' evaluations, and a configuration with fewer variants
    # reports only its own, not the assets an earlier configuration left in the run folders
    assert main(argv) == 0
    assert capsys.readouterr().out.count("finished before with these settings, reusing its evaluation") == 2
    assert json.loads((out / f"results-{tag}.json").read_text())["models"] == report["models"]
    assert (
        main(
            argv[: argv.index("--variants") + 1]
            + ["full"]
            + argv[argv.index("--variants") + 3 : -3]
            + ["--tag", "fewer", "--out", str(out), "--no-progress"]
        )
        == 0
    )
    fewer = json.loads((out / "results-paper-fewer.json").read_text())
    assert set(fewer["models"]["paper"]["objects"][0]["figures"]["relight"]) == {"full"}
    # the default configuration runs in `runs/paper`, its geometry trained on the model's normals; another
    # configuration of the default method starts from its predictions, geometry and lift and keeps them where its
    # settings leave them unchanged
    base = [*ONE_OBJECT, "--variants", "proj-average", "--out", str(out), "--no-progress"]
    assert main(base) == 0
    assert "geometry shared from" not in capsys.readouterr().out and (runs / "paper" / "lift" / "stage.json").exists()
    assert '"predicted_normal_weight": 1.0' in (runs / "paper" / "geometry" / "stage.json").read_text()
    assert main(base + ["--without", "light-warmup"]) == 0
    assert "starts from paper's materials2d, geometry, lift (redone where" in capsys.readouterr().out
    other = next(p for p in runs.glob("paper-matspray-*"))
    assert (other / "lift" / "stage.json").read_text() == (runs / "paper" / "lift" / "stage.json").read_text()
    assert not {"materials2d", "lift", "geometry"} & set(
        json.loads((other / "timings.json").read_text())
    )  # reused, not redone


def test_resolution_renders_and_trains_the_objects_at_that_size(tmp_path):
    pytest.importorskip("mitsuba")
    out = tmp_path / "g"
    argv = [*ONE_OBJECT, "--geometry-only"]
    assert main([*argv, "--resolution", "24", "--out", str(out), "--no-progress"]) == 0
    data = out / "objects" / "dev-00-seed1000" / "data"
    assert read_image(data / "train" / "r_000.png")[0].shape[:2] == (24, 24)
    record = json.loads(
        (out / "objects" / "dev-00-seed1000" / "runs" / "paper" / "geometry" / "stage.json").read_text()
    )
    assert record["settings"]["resolution"] == 24
    assert parse_args([*argv, "--resolution", "256"]).out == Path("runs") / "generalise-dev-test-256px"
    assert parse_args(argv).out == Path("runs") / "generalise-dev-test"
