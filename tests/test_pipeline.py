"""The method end to end on a tiny Mitsuba object: stages, artifacts, resuming, eval, report, relight. The tests on
it take `tiny_object` (tests/conftest.py: made with Mitsuba, or one made elsewhere, else they skip); the others run
without Mitsuba."""

import re
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from matspray.errors import NumericalError, RunError
from matspray.method.config import build_config, shadow_maps
from matspray.method.pipeline import Pipeline
from matspray.method.refine.loop import check_finite
from matspray.presets import VARIANT_NAMES as VARIANTS
from matspray.presets import WORKING_SIZE, asset_stage, get_variant
from matspray.rundir import RunDir
from tests.conftest import busy_message, run_cli
from tests.reference_metrics import relighting_psnr


def tiny_config():  # with baked shadows (off by default), so that the run exercises every stage
    return build_config("test", predictor="simulated", **{"refine.iterations": 8, "visibility": shadow_maps("test")})


@pytest.fixture(scope="module")
def finished_run(tiny_object, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "run"
    pipeline = Pipeline(tiny_object, run, tiny_config(), progress=False, log=lambda _: None)
    pipeline.run_all(VARIANTS)
    return run


def test_eval_refuses_the_capture_flags_on_a_dataset_with_ground_truth(finished_run):
    result = run_cli("eval", "--run", finished_run, "--env", "studio", "--credit", "me")
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "matspray eval: error: --env and --credit are for runs on a capture without ground truth; this dataset has it"
    )


def test_every_stage_writes_its_artifact(finished_run):
    for path in (
        "config.yaml",
        "dataset.json",
        "timings.json",
        "materials2d/predictor.json",
        "geometry/gaussians.ply",
        "lift/projected.pt",
        "visibility/visibility.pt",
        "asset/asset.ply",
        "asset/envmap.exr",
        "asset/merger.pt",
        "asset/visibility.pt",
    ):
        assert (finished_run / path).exists(), path
    for variant in VARIANTS:
        assert (finished_run / asset_stage(variant) / "asset.ply").exists()
    timings = (finished_run / "timings.json").read_text()
    for stage in ("materials2d", "geometry", "lift", "visibility", "asset"):
        assert f'"{stage}"' in timings
    assert not list(finished_run.rglob("*.tmp-*")), "a temporary file was left behind"


def test_asset_round_trip(finished_run):
    from matspray.method.asset import read_asset

    asset = read_asset(finished_run / "asset")
    assert asset.materials.shape[1] == 5 and len(asset.gaussians) == len(asset.materials)
    assert (asset.materials >= 0).all() and (asset.materials <= 1).all()
    assert torch.allclose(asset.normals.norm(dim=-1), torch.ones(len(asset.normals)), atol=1e-4)
    assert asset.visibility is not None and asset.visibility.shape == (
        len(asset.gaussians),
        2 * 4 * 4,
    )  # test preset: rows 4


def test_the_asset_ply_carries_the_refined_normals_of_the_variants_with_the_pbr_loss(finished_run):
    """The PBR variants' normals were trained (they left the geometry's, averaged over their neighbours); the others
    shade with the geometry's normals averaged over their neighbours (`refine.normal_neighbours`, on by default)."""
    from matspray.geometry.ply import read_ply
    from matspray.method.asset import read_asset
    from matspray.method.lift import load_lift
    from matspray.method.refine.loop import RefineConfig
    from matspray.method.refine.normals import angle_change_degrees, smoothed_normals

    gaussians, geometry_normals = read_ply(finished_run / "geometry" / "gaussians.ply")
    lifted = load_lift(finished_run / "lift" / "projected.pt", "cpu")
    kept = gaussians.subset(lifted.kept)
    normals = torch.nn.functional.normalize(geometry_normals, dim=-1)[lifted.kept]
    start = smoothed_normals(normals, kept.means, kept.opacities, RefineConfig().normal_neighbours)
    for variant in VARIANTS:
        turned = angle_change_degrees(start, read_asset(finished_run / asset_stage(variant)).normals)
        if get_variant(variant).learns_light:  # full, no-softmax and the two without maps
            assert float(turned.max()) > 0.2, variant  # 8 steps of Adam at 1e-3 rad: up to 0.46 degrees
        else:
            assert float(turned.max()) < 0.05, variant  # the PLY's float32 round trip


def test_the_simulated_predictors_normal_maps_reach_refinement_in_world_space(tiny_object, finished_run):
    """The simulated predictor writes normal maps beside the materials; refinement reads them in world space (near
    the true normals), and with a weight on them its history has their term."""
    from matspray.geometry.evaluate import true_normals
    from matspray.method.refine.loop import refine
    from matspray.method.refine.normals import angle_change_degrees

    config = replace(tiny_config(), visibility=None)
    config = replace(config, refine=replace(config.refine, predicted_normal_weight=1.0, iterations=3))
    pipeline = Pipeline(tiny_object, finished_run, config, progress=False, log=lambda _: None)
    inputs = pipeline.refine_inputs()
    assert inputs.normal_maps is not None and len(inputs.normal_maps) == len(inputs.views)
    view, predicted = inputs.views[0], inputs.normal_maps[0]
    truth, on_object = true_normals(view), view.alpha > 0.5
    assert float(angle_change_degrees(predicted[on_object], truth[on_object]).mean()) < 20.0
    history = refine(inputs, replace(config.refine, log_every=1), progress=False).history
    assert "predicted_normals" in history[-1]


def test_maps_without_normals_refine_without_them_and_say_so(tiny_object, tmp_path):
    """The predicted-normal weights are on by default; a run whose 2D maps have no normal maps (here: a dataset without
    true normals, from which the simulated predictor makes none) trains and refines without them, with one line each
    naming the folder, and its fingerprints are those of the weights at 0."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_object, data)
    for normal in data.rglob("*_normal.exr"):
        normal.unlink()
    config = replace(tiny_config(), visibility=None)
    assert config.geometry.predicted_normal_weight > 0 and config.refine.predicted_normal_weight > 0  # the defaults
    lines = []
    pipeline = Pipeline(data, tmp_path / "run", config, progress=False, log=lines.append)
    inputs = pipeline.refine_inputs()
    assert inputs.normal_maps is None
    folder = str(tmp_path / "run" / "materials2d")
    for stage in ("geometry", "refinement"):
        assert [line for line in lines if line.startswith(f"{stage}: the 2D maps ({folder}) have no normal maps")]
    off = replace(
        config,
        geometry=replace(config.geometry, predicted_normal_weight=0.0),
        refine=replace(config.refine, predicted_normal_weight=0.0),
    )
    with Pipeline(data, tmp_path / "run", off, progress=False, log=lambda _: None) as without:
        assert without.geometry_plan().fingerprint == pipeline.geometry_plan().fingerprint
        assert without.resolved().refine["full"].fingerprint == pipeline.resolved().refine["full"].fingerprint
    pipeline.close()


def test_only_variants_that_read_the_maps_refine_towards_their_normals(tiny_object, finished_run):
    pipeline = Pipeline(tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None)
    assert pipeline.plan.normals is True
    assert pipeline.resolved().refine["full"].settings.predicted_normal_weight == 1.0
    no_prior = pipeline.resolved().refine["no-prior"].settings  # the variant without a 2D prior
    assert no_prior.predicted_normal_weight == 0.0
    pipeline.close()


def test_a_run_is_unshadowed_by_default(tiny_object, finished_run, tmp_path):
    from matspray.method.asset import read_asset

    run = rerun_from_slow_stages(tiny_object, finished_run, tmp_path)
    assert not (run / "visibility").exists()
    assert read_asset(run / "asset").visibility is None


def test_a_run_records_the_peak_memory_of_each_stage_and_prints_it(tiny_object, finished_run, tmp_path, capsys):
    import json

    from matspray.memory import peak_rss_bytes

    run = rerun_from_slow_stages(tiny_object, finished_run, tmp_path)
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("peak memory: ")]
    assert len(lines) == 1
    if peak_rss_bytes() is None:
        return  # no /proc: nothing is measured, and the line says "unknown"
    record = json.loads((run / "asset" / "stage.json").read_text())
    assert 50 < record["peak_memory_mib"] < 64 * 1024  # the whole process: torch alone is over 50 MiB
    assert RunDir(run).peak_memory()["asset"] == record["peak_memory_mib"]
    assert f"asset {record['peak_memory_mib'] / 1024:.2f}" in lines[0]


def test_second_run_reuses_every_stage(tiny_object, finished_run):
    messages = []
    Pipeline(tiny_object, finished_run, tiny_config(), progress=False, log=messages.append).run_all(VARIANTS)
    assert any("reusing asset/" in m for m in messages)
    assert not any(m.startswith("geometry: 3D") for m in messages)


def test_run_folder_of_another_dataset_is_refused(tmp_path, finished_run):
    pytest.importorskip("mitsuba")  # the other dataset is made here (finished_run's object may be one made elsewhere)
    from matspray.synth import SynthConfig, make_object

    other = tmp_path / "other"
    make_object(
        SynthConfig(shape="sphere", seed=2, resolution=16, train_views=3, test_views=1, spp=2, env_height=16),
        other,
        progress=False,
        notify=lambda _: None,
    )
    with pytest.raises(RunError, match="made from another dataset"):
        Pipeline(other, finished_run, tiny_config(), progress=False, log=lambda _: None)


def test_eval_tables_and_report(tiny_object, finished_run):
    from matspray.eval.report import write_report
    from matspray.eval.run_eval import evaluate_run

    metrics = evaluate_run(finished_run, tiny_object, progress=False)
    assert set(metrics["variants"]) == set(VARIANTS)
    summary = metrics["variants"]["full"]["summary"]
    assert summary["relighting"]["psnr"] == pytest.approx(relighting_psnr(finished_run, tiny_object), abs=1e-6)
    assert 0 < summary["relighting"]["ssim"] <= 1
    tables = (finished_run / "eval" / "tables.md").read_text()
    assert "Table 1" in tables and "Proj. Average" in tables and "Without Softmax" in tables
    assert "# MatSpray evaluation: sphere (seed 1)" in tables and str(tiny_object) not in tables  # shareable
    report = write_report(finished_run, metrics, tiny_object)
    page = report.read_text()
    sources = re.findall(r'src="([^"]+)"', page)
    assert len(sources) > 10
    missing = [s for s in sources if not (report.parent / s).exists()]
    assert not missing, f"report references files that do not exist: {missing}"
    assert "SIMULATED" in page
    assert "2D prediction" in page and any("pred2d_test_" in s for s in sources)  # the test views' own 2D baseline
    # the answer first, titled by the object, with a glossary, and no path of the machine
    assert max(page.index('id="headline"'), page.index('id="summary-relit"')) < page.index("<h2>Test views</h2>")
    assert "<h1>MatSpray result: sphere (seed 1)</h1>" in page and '<h2 id="glossary">' in page
    for path in ("/tmp", "/root", "/home", str(finished_run), str(tiny_object), str(Path.home())):
        assert path not in page, path


def test_relight_cli_writes_frames_and_video(finished_run, tmp_path):
    out = tmp_path / "relit"
    views = ("--views", "orbit", "--frames", "3")
    result = run_cli("relight", "--run", finished_run, "--env", "studio", *views, "--out", out, timeout=300)
    assert result.returncode == 0, result.stderr
    assert len(list(out.glob("orbit_*_studio.png"))) == 3
    assert (out / "orbit_studio.mp4").stat().st_size > 0


def test_relight_refuses_a_map_that_is_not_latlong(finished_run, tmp_path):
    from matspray.data import write_image

    write_image(tmp_path / "square.exr", torch.ones(8, 8, 3))
    result = run_cli(
        "relight", "--run", finished_run, "--env", tmp_path / "square.exr", "--out", tmp_path / "o", timeout=300
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "lat-long" in result.stderr


def test_eval_refuses_a_folder_that_is_not_a_run(tmp_path):  # needs no run, so none is made (nor Mitsuba)
    from matspray.eval.run_eval import evaluate_run

    with pytest.raises(RunError, match="not a MatSpray run folder"):
        evaluate_run(tmp_path, None)


def test_eval_needs_ground_truth(tiny_object, finished_run, tmp_path):
    """The run's own dataset with its test views' material maps taken away: evaluation refuses, naming the views."""
    import shutil

    from matspray.errors import DataError
    from matspray.eval.run_eval import evaluate_run

    data = tmp_path / "data"
    shutil.copytree(tiny_object, data)
    for path in (data / "test").glob("*_basecolor.png"):
        path.unlink()
    with pytest.raises(DataError, match=r"test views without ground-truth material maps: r_000, r_001 \("):
        evaluate_run(finished_run, data, progress=False)


def test_nan_loss_names_step_and_term():
    with pytest.raises(NumericalError, match="refine step 7: the photo loss is nan"):
        check_finite(7, material=torch.tensor(0.1), photo=torch.tensor(float("nan")))


def test_a_pipeline_from_default_configs_runs(tiny_object, tmp_path):
    from matspray.method.config import PipelineConfig

    pipeline = Pipeline(
        tiny_object, tmp_path / "run", PipelineConfig(predictor="ground-truth"), progress=False, log=lambda _: None
    )
    maps = pipeline.predict()
    assert set(maps) == {v.name for v in pipeline.scene.train}
    assert pipeline.config.geometry.iterations == 3000  # the demo preset's geometry, not None


def test_resuming_with_the_other_method_recomputes_only_what_differs(tiny_object, finished_run):
    ours = Pipeline(tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None)
    paper = Pipeline(
        tiny_object,
        finished_run,
        build_config("test", "paper", predictor="simulated", **{"refine.iterations": 8}),
        progress=False,
        log=lambda _: None,
    )
    assert paper.plan.predict.fingerprint == ours.plan.predict.fingerprint
    # the paper starts the geometry from random points and trains it without the predicted normals
    assert paper.geometry_plan().fingerprint != ours.geometry_plan().fingerprint
    assert paper.resolved().lift.fingerprint != ours.resolved().lift.fingerprint
    same_geometry = {"geometry.init": "hull", "geometry.predicted_normal_weight": 1.0, "refine.iterations": 8}
    paper_on_ours = Pipeline(
        tiny_object,
        finished_run,
        build_config("test", "paper", predictor="simulated", **same_geometry),
        progress=False,
        log=lambda _: None,
    )
    assert paper_on_ours.geometry_plan().fingerprint == ours.geometry_plan().fingerprint  # the geometry is reused
    # the same lift settings under another method name still do not share the stage: the method is in the fingerprint
    relabelled = Pipeline(
        tiny_object, finished_run, replace(tiny_config(), method="paper"), progress=False, log=lambda _: None
    )
    assert relabelled.resolved().lift.fingerprint != ours.resolved().lift.fingerprint
    Pipeline(
        tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None
    )  # leave config.yaml as the fixture's


def test_the_simulated_predictor_draws_from_the_objects_seed_and_says_so(tiny_object, finished_run):
    import json

    record = json.loads((finished_run / "materials2d" / "stage.json").read_text())
    assert record["settings"]["seed"] == 1  # tiny_object is synth seed 1; the config gives no seed
    pipeline = Pipeline(tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None)
    assert pipeline.plan.predictor_options.seed == 1

    def given(seed: int) -> Pipeline:  # the run with the predictor's seed given in the config
        config = replace(tiny_config(), predictor_options={"seed": seed})
        return Pipeline(tiny_object, finished_run, config, progress=False, log=lambda _: None)

    given_zero = given(0)
    assert given_zero.plan.predictor_options.seed == 0
    assert given_zero.plan.predict.fingerprint != pipeline.plan.predict.fingerprint  # other draws: predict runs again
    given_one = given(1)
    assert given_one.plan.predictor_options == pipeline.plan.predictor_options
    Pipeline(
        tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None
    )  # leave config.yaml as the fixture's


def test_a_light_probe_is_shaded_with_as_given_and_a_missing_one_is_refused_first(
    tiny_object, finished_run, tmp_path, capsys
):
    import json
    import os
    import shutil

    from matspray.cli import main
    from matspray.render.shade.envmap import EnvironmentMap

    run = tmp_path / "run"
    for stage in ("materials2d", "geometry"):  # reuse the slow stages
        shutil.copytree(finished_run / stage, run / stage)
    shutil.copy(finished_run / "timings.json", run / "timings.json")
    name = json.loads((tiny_object / "scene.json").read_text())["lights"]["train"]
    probe = tmp_path / "probe.exr"
    shutil.copy(tiny_object / "envmaps" / f"{name}.exr", probe)
    args = ["run", "--data", str(tiny_object), "--out", str(run), "--preset", "test", "--set", "refine.iterations=4"]

    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert main(args + ["--set", f"light_probe={tmp_path / 'nowhere.exr'}"]) == 2
    assert "nowhere.exr" in capsys.readouterr().err  # refused before the run folder is touched
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before

    assert main(args + ["--set", f"light_probe={probe}"]) == 0
    expected = EnvironmentMap.from_file(probe, height=8).map  # the test preset's light size
    assert torch.allclose(EnvironmentMap.from_file(run / "asset" / "envmap.exr").map, expected, rtol=1e-3, atol=1e-6)
    capsys.readouterr()
    assert main(args + ["--set", f"light_probe={probe}"]) == 0
    assert "refine [full]: done before" in capsys.readouterr().out
    os.utime(probe, ns=(probe.stat().st_atime_ns, probe.stat().st_mtime_ns + 10**9))  # a changed probe refines again
    assert main(args + ["--set", f"light_probe={probe}"]) == 0
    assert "refine [full]: done before" not in capsys.readouterr().out


def test_a_run_folder_another_process_writes_is_refused_and_left_as_it_was(
    tiny_object, finished_run, tmp_path, capsys, hold_in_another_process
):
    import shutil

    from matspray.cli import main

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    holder = hold_in_another_process(run)
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    args = ["run", "--data", str(tiny_object), "--out", str(run), "--preset", "test", "--set", "refine.iterations=4"]
    assert main(args) == 2
    assert capsys.readouterr().err.strip().endswith(busy_message(run, holder.pid))
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == before  # not even config.yaml rewritten
    holder.kill()
    holder.wait()
    assert main(args) == 0


def test_photos_larger_than_the_working_size_are_brought_to_it(tiny_object, tmp_path, monkeypatch):
    monkeypatch.setitem(WORKING_SIZE, "test", 16)  # the object is 32 px
    said = []
    with Pipeline(tiny_object, tmp_path / "small", build_config("test"), progress=False, log=said.append) as pipeline:
        assert (pipeline.scene.train[0].width, pipeline.scene.train[0].height) == (
            16,
            16,
        ) and pipeline.config.downscale == 2.0
    assert (
        "photos: 32x32 brought to 16x16, the test preset's working size (--downscale 1 keeps them as they are)" in said
    )
    assert (
        pipeline.run.downscale() == 2.0
    )  # config.yaml keeps the factor, so eval, relight and export load the same views
    with Pipeline(
        tiny_object, tmp_path / "full", build_config("test", downscale=1.0), progress=False, log=lambda _: None
    ) as pipeline:
        assert pipeline.scene.train[0].width == 32  # --downscale given: kept as asked


def test_run_says_its_estimate_first_and_counts_only_what_is_left(tiny_object, finished_run, tmp_path, capsys):
    from matspray.cli import main

    assert Pipeline(tiny_object, finished_run, tiny_config(), progress=False, log=lambda _: None).work(
        VARIANTS
    ).stages() == {
        "points": 0.0,
        "geometry": 0.0,
        "masks": 0.0,
        "lift": 0.0,
        "refine": 0.0,
        "refine-mapless": 0.0,
    }  # everything finished
    run = tmp_path / "fresh"
    assert (
        main(
            [
                "run",
                "--data",
                str(tiny_object),
                "--out",
                str(run),
                "--preset",
                "test",
                "--set",
                "geometry.iterations=5",
                "--set",
                "refine.iterations=3",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out.splitlines()
    assert (
        printed[0].startswith("estimate: ") and " with 2 free CPU cores " in printed[0] and "geometry ~" in printed[0]
    ), printed
    assert any(line.startswith("took ") for line in printed)


def test_the_variants_of_a_run_share_the_frozen_views_and_a_light_warm_up_that_starts_alike(
    tiny_object, finished_run, tmp_path, monkeypatch
):
    import shutil

    from matspray.method import pipeline as pipeline_module
    from matspray.method.asset import read_asset

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    trained = ("full", "no-softmax", "no-prior")
    for variant in trained:
        shutil.rmtree(run / asset_stage(variant))
    builds = []

    def counted(inputs):
        builds.append(len(inputs.views))
        return frozen_views(inputs)

    frozen_views = pipeline_module.frozen_views
    monkeypatch.setattr(pipeline_module, "frozen_views", counted)
    from matspray.method.refine import loop as refine_module

    warm_ups = []
    warm_up_light = refine_module.warm_up_light
    monkeypatch.setattr(refine_module, "warm_up_light", lambda *a: warm_ups.append(1) or warm_up_light(*a))
    Pipeline(tiny_object, run, tiny_config(), progress=False, log=lambda _: None).run_all(trained)
    assert len(builds) == 1
    assert len(warm_ups) == 2  # full's, reused by no-softmax (which starts from the same average); no-prior's
    for variant in trained:  # the same materials as the fixture's run, which built them once per variant
        shared, own = read_asset(run / asset_stage(variant)), read_asset(finished_run / asset_stage(variant))
        torch.testing.assert_close(shared.materials, own.materials, rtol=0, atol=0)


def test_a_run_with_backend_numba_compiles_its_kernels_while_it_reads_its_data(tiny_object, tmp_path, monkeypatch):
    from matspray.method import pipeline as pipeline_module

    started = []
    monkeypatch.setattr(pipeline_module, "compile_in_background", lambda: started.append(True))
    Pipeline(tiny_object, tmp_path / "torch", replace(tiny_config(), backend="torch"), progress=False, log=print)
    assert started == []
    Pipeline(tiny_object, tmp_path / "numba", replace(tiny_config(), backend="numba"), progress=False, log=print)
    assert started == [True]


def test_the_mergers_precision_is_part_of_the_refinement_and_its_record(tiny_object, finished_run, tmp_path):
    import json

    fingerprints = {}
    for precision in ("float32", "bfloat16"):
        config = replace(tiny_config(), refine=replace(tiny_config().refine, merger=replace(
            tiny_config().refine.merger, precision=precision)))  # fmt: skip
        pipeline = Pipeline(tiny_object, tmp_path / precision, config, progress=False, log=lambda _: None)
        fingerprints[precision] = pipeline.resolved().refine["full"].fingerprint
    assert fingerprints["float32"] != fingerprints["bfloat16"]
    record = json.loads((finished_run / "asset" / "stage.json").read_text())
    # finished_run's precision is "auto": bfloat16 on a CPU that multiplies it in hardware (AVX512-BF16 or AMX). The
    # CPU's features are read from the kernel's list here, not asked of torch as the merger does
    assert tiny_config().refine.merger.precision == "auto"
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.is_file():
        pytest.skip("no /proc/cpuinfo to tell whether this CPU multiplies bfloat16 in hardware")
    flags = set(re.findall(r"^flags\s*:(.*)$", cpuinfo.read_text(), re.MULTILINE)[0].split())
    native = bool(flags & {"avx512_bf16", "amx_tile", "amx_bf16"})
    assert record["merger_precision"] == ("bfloat16" if native else "float32"), sorted(flags)


def test_a_geometry_finished_with_other_inputs_or_settings_is_trained_again_not_kept(tiny_object, tmp_path):
    def trained(run: Path, config) -> tuple[bytes, str]:  # the Gaussians' file and the stage's fingerprint
        with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
            pipeline.geometry()
            return (run / "geometry" / "gaussians.ply").read_bytes(), pipeline.geometry_plan().fingerprint

    first, first_fp = trained(tmp_path / "run", tiny_config())
    # other predictions (their normals supervise the geometry), the same geometry settings: the finished training's
    # checkpoint matches every setting, and resuming it kept the old Gaussians under the new fingerprint
    other_maps = replace(tiny_config(), predictor_options={"seed": 7})
    again, again_fp = trained(tmp_path / "run", other_maps)
    fresh, _ = trained(tmp_path / "fresh", other_maps)
    assert again_fp != first_fp and again != first and again == fresh
    assert RunDir(tmp_path / "run").stage_fingerprint("geometry") == again_fp
    # another geometry setting in the same folder: trained again, where the checkpoint was refused before
    fewer = replace(other_maps, geometry=replace(other_maps.geometry, max_gaussians=500))
    smaller, _ = trained(tmp_path / "run", fewer)
    assert smaller == trained(tmp_path / "fresh-fewer", fewer)[0] != again
    # interrupted after its checkpoint, before its record: the checkpoint of other predictions was resumed (finished,
    # so its Gaussians kept) where the stage record had gone; it carries its inputs now, and is trained over
    RunDir(tmp_path / "run").reopen_stage("geometry")
    resumed, _ = trained(tmp_path / "run", other_maps)
    assert resumed == again != smaller


def rerun_from_slow_stages(tiny_object, finished_run, tmp_path):
    """A run of the test preset (4 refinement steps) that reuses `finished_run`'s predictions and geometry."""
    import shutil

    from matspray.cli import main

    run = tmp_path / "run"
    for stage in ("materials2d", "geometry"):  # reuse the slow stages
        shutil.copytree(finished_run / stage, run / stage)
    shutil.copy(finished_run / "timings.json", run / "timings.json")
    args = ["run", "--data", str(tiny_object), "--out", str(run), "--preset", "test", "--set", "refine.iterations=4"]
    assert main(args) == 0
    return run


def test_a_run_with_a_camera_light_says_so_records_it_and_keeps_it_with_the_asset(tiny_object, finished_run, tmp_path):
    import json
    import shutil

    from matspray.method.asset import read_asset

    run = tmp_path / "run"
    for stage in ("materials2d", "geometry", "visibility"):  # reuse the slow stages
        shutil.copytree(finished_run / stage, run / stage)
    config = replace(tiny_config(), refine=replace(tiny_config().refine, camera_light="on"))
    said = []
    with Pipeline(tiny_object, run, config, progress=False, log=said.append) as pipeline:
        pipeline.refine("full")
        views = len(pipeline.refine_inputs().views)
    flash = [line for line in said if "lit by a flash" in line]
    assert len(flash) == 1 and f"{views} of {views} training photos" in flash[0], said
    assert "refine.camera_light=on" in flash[0]
    record = json.loads((run / "asset" / "stage.json").read_text())["camera_light"]
    asset = read_asset(run / "asset")
    assert record["lit_views"] == views and record["intensity"] == [
        round(float(x), 4) for x in asset.camera_light.intensity
    ]
    assert asset.camera_light.views == "on"
    assert not (finished_run / "asset" / "camera_light.json").exists()  # the default on PNG renders: no flash
