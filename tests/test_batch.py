"""`matspray batch`: many tiny objects on a local Ray (two workers), failure isolation, resuming,
the summary's averages, the in-process fallback without Ray, and bad input."""

import json
import math
import shutil
import socket
import sys
import time
from pathlib import Path

import pytest

from matspray.batch import BatchConfig, batch_objects, run_batch, summary_markdown
from matspray.batch.cluster import address_endpoint, check_reachable
from matspray.batch.runner import claim_batch_folder
from matspray.cli import build_parser, main
from matspray.cli.batch import batch_config
from matspray.errors import ConfigError, RunError, SettingError
from matspray.eval.tables import average_tables
from tests.conftest import make_tiny_object, run_cli
from tests.reference_metrics import relighting_psnr
from tests.viewer_process import free_port

REPO = Path(__file__).resolve().parents[1]
TINY = ["--preset", "test", "--set", "refine.iterations=8", "--set", "geometry.iterations=150"]


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    pytest.importorskip("mitsuba")
    root = tmp_path_factory.mktemp("objects")
    for name, shape, seed in (("ball", "sphere", 1), ("ring", "torus", 2)):
        make_tiny_object(root / name, shape=shape, seed=seed)
    (root / "broken").mkdir()
    (root / "broken" / "transforms_train.json").write_text("{not json")
    return root


@pytest.fixture(scope="module")
def ray_local():
    """One small local Ray for the module (2 CPUs, 100 MB object store), shut down afterwards."""
    ray = pytest.importorskip("ray")
    ray.init(
        num_cpus=2,
        object_store_memory=100 * 1024**2,
        include_dashboard=False,
        logging_level="ERROR",
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}},
    )
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def first_batch(objects, ray_local, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    datas = [str(objects / n) for n in ("ball", "ring", "broken")]
    start = time.perf_counter()
    code = main(["batch", *datas, "--out", str(out), "--workers", "2", *TINY])
    return out, datas, code, time.perf_counter() - start


def test_two_workers_run_the_objects_side_by_side_and_a_broken_dataset_fails_alone(first_batch, objects):
    out, _, code, _ = first_batch
    assert code == 1  # one object failed
    summary = json.loads((out / "summary.json").read_text())
    rows = {r["name"]: r for r in summary["objects"]}
    assert [r["name"] for r in summary["objects"]] == ["ball", "ring", "broken"]
    assert rows["ball"]["status"] == rows["ring"]["status"] == "finished"
    assert rows["broken"]["status"] == "failed" and "transforms_train.json" in rows["broken"]["error"]
    assert "\n" not in rows["broken"]["error"] and "Traceback" not in rows["broken"]["error"]
    assert summary["failed"] == [{"name": "broken", "error": rows["broken"]["error"]}]
    assert "Ray local, 2 workers" in summary["engine"]
    for name in ("ball", "ring"):
        assert (out / name / "asset" / "asset.ply").exists() and (out / name / "eval" / "metrics.json").exists()
        assert set(rows[name]["stage_seconds"]) >= {"geometry", "lift", "asset"}
        backend = json.loads((out / name / "asset" / "stage.json").read_text())["backend"]  # the run's, eval's too
        reference = relighting_psnr(Path(rows[name]["run"]), objects / name, "full", backend)
        assert rows[name]["metrics"]["relighting"]["psnr"] == pytest.approx(reference, abs=1e-6)
    (a0, a1), (b0, b1) = rows["ball"]["span"], rows["ring"]["span"]
    assert a0 < b1 and b0 < a1, "the two objects did not run at the same time"
    md = (out / "summary.md").read_text()
    assert "| broken | FAILED |" in md and "## Failures" in md and "Averages over 2 objects" in md


def test_summary_averages_equal_a_hand_computation(first_batch):
    out = first_batch[0]
    summary = json.loads((out / "summary.json").read_text())
    per_object = [
        json.loads((out / n / "eval" / "metrics.json").read_text())["table1"]["Ours"] for n in ("ball", "ring")
    ]
    averaged = summary["averages"]["table1"]["Ours"]
    assert summary["averaged_over"] == 2
    for row in ("relighting", "basecolor", "roughness"):
        for metric in ("psnr", "ssim", "lpips"):
            values = [m[row][metric] for m in per_object]
            if None in values:  # LPIPS is left out (None) where its weights are absent, and so is its average
                assert metric == "lpips" and values == [None, None] and averaged[row][metric] is None
            else:
                assert averaged[row][metric] == pytest.approx(sum(values) / 2, rel=1e-12)
    finite = [m["metallic"]["psnr"] for m in per_object if math.isfinite(m["metallic"]["psnr"])]
    assert averaged["metallic"]["psnr_infinite"] == 2 - len(finite)
    assert averaged["metallic"]["psnr"] == pytest.approx(sum(finite) / len(finite) if finite else math.inf)


def test_metallic_infinity_rule_in_the_averages_and_the_summary():
    def metrics(relight, metallic):
        return {
            "table1": {
                "Ours": {
                    "relighting": {"psnr": relight, "ssim": 0.5, "lpips": 0.1},
                    "metallic": {"psnr": metallic, "ssim": 1.0, "lpips": 0.0},
                }
            }
        }

    averaged = average_tables([metrics(20.0, math.inf), metrics(30.0, 24.0), metrics(25.0, 30.0)])["table1"]["Ours"]
    assert averaged["relighting"]["psnr"] == pytest.approx(25.0)
    assert averaged["metallic"] == {"psnr": 27.0, "ssim": 1.0, "lpips": 0.0, "psnr_infinite": 1, "objects": 3}
    assert average_tables([metrics(20.0, math.inf)])["table1"]["Ours"]["metallic"]["psnr"] == math.inf
    rows = [
        {
            "name": "a",
            "status": "finished",
            "error": None,
            "seconds": 1.0,
            "stage_seconds": {},
            "metrics": {"metallic": {"psnr": math.inf}},
        }
    ]
    md = summary_markdown(
        {
            "title": "t",
            "engine": "e",
            "wall_seconds": 1.0,
            "objects": rows,
            "failed": [],
            "averaged_over": 1,
            "averages": {"table1": {"Ours": averaged}},
        }
    )
    assert "∞" in md and "∞*/27.000" in md


def test_rerun_skips_finished_objects_and_retries_the_failed_one(first_batch, capsys):
    out, datas, _, first_seconds = first_batch
    before = {n: (out / n / "timings.json").read_text() for n in ("ball", "ring")}
    start = time.perf_counter()
    assert main(["batch", *datas, "--out", str(out), "--workers", "2", *TINY]) == 1
    seconds = time.perf_counter() - start
    summary = json.loads((out / "summary.json").read_text())
    assert [r["status"] for r in summary["objects"]] == ["skipped", "skipped", "failed"]
    assert {n: (out / n / "timings.json").read_text() for n in ("ball", "ring")} == before
    assert summary["averaged_over"] == 2  # finished objects still count in the averages
    assert seconds < first_seconds / 2
    err = capsys.readouterr().err
    assert "failed: broken:" in err


def test_other_settings_in_the_same_folder_are_refused(first_batch, capsys):
    out, datas = first_batch[:2]
    code = main(
        [
            "batch",
            *datas[:1],
            "--out",
            str(out),
            "--preset",
            "test",
            "--set",
            "refine.iterations=9",
            "--set",
            "geometry.iterations=150",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "other settings" in err and "refine.iterations 9 here, 8 there" in err
    with pytest.raises(RunError, match="other settings"):
        claim_batch_folder(out, {"pipeline": {}, "variants": ["full"]})


def test_a_setting_added_since_at_its_unset_default_does_not_refuse_the_folder(tmp_path):
    claim_batch_folder(tmp_path, {"pipeline": {"preset": "demo"}, "variants": ["full"]})  # an older version's record
    claim_batch_folder(tmp_path, {"pipeline": {"preset": "demo", "object_bounds": None}, "variants": ["full"]})
    with pytest.raises(
        RunError, match=r"pipeline.preset 'test' here, 'demo' there; pipeline.seed 1 here, absent there"
    ):
        claim_batch_folder(tmp_path, {"pipeline": {"preset": "test", "seed": 1}, "variants": ["full"]})
    with pytest.raises(RunError, match=r"object_bounds \[0.0, 0.0, 0.0, 1.0\] here, None there"):
        claim_batch_folder(
            tmp_path, {"pipeline": {"preset": "demo", "object_bounds": [0.0, 0.0, 0.0, 1.0]}, "variants": ["full"]}
        )


def test_without_ray_the_objects_run_in_process_and_resume_an_interrupted_run(
    first_batch, objects, tmp_path, monkeypatch
):
    out = first_batch[0]
    shutil.copytree(
        out / "ball", tmp_path / "ball"
    )  # an interrupted object: its stages are there, its refinement is not
    shutil.rmtree(tmp_path / "ball" / "asset")
    (tmp_path / "ball" / "batch-object.json").unlink()
    (tmp_path / "ball" / "batch.log").unlink()
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails
    config = batch_config(build_parser().parse_args(["batch", "unused", "--out", "unused", "--workers", "2", *TINY]))
    messages = []
    summary = run_batch([objects / "ball"], tmp_path, config, progress=False, log=messages.append)
    assert summary["objects"][0]["error"] is None
    assert any("Ray is not installed" in m and "one after another" in m for m in messages)
    assert summary["engine"].startswith("in-process") and summary["objects"][0]["status"] == "finished"
    log = (tmp_path / "ball" / "batch.log").read_text()
    assert "geometry: done before" in log and "lift: done before" in log
    assert (tmp_path / "ball" / "asset" / "asset.ply").exists()


# ------------------------------------------------------------------------------ bad input, no Ray needed
def test_workers_below_one_is_one_line(tmp_path, capsys):
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "out"), "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "matspray batch: error: --workers: must be >= 1, got 0"
    with pytest.raises(SettingError, match="workers: must be >= 1"):
        run_batch([tmp_path], tmp_path / "out", BatchConfig(workers=0))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("gpus", ["nan", "inf", "-1"])
def test_gpus_per_object_must_be_a_finite_share(tmp_path, capsys, gpus):
    """NaN passed the `< 0` check and ended in a traceback from inside Ray."""
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "out"), "--gpus-per-object", gpus]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"matspray batch: error: --gpus-per-object: must be a finite number >= 0, got {float(gpus):g}"
    assert not (tmp_path / "out").exists()


def test_two_inputs_with_one_name_are_refused(tmp_path, capsys):
    (tmp_path / "a" / "chair").mkdir(parents=True)
    (tmp_path / "b" / "chair").mkdir(parents=True)
    with pytest.raises(ConfigError, match=r"two datasets are named 'chair'.*rename one"):
        batch_objects([tmp_path / "a" / "chair", tmp_path / "b" / "chair"], tmp_path / "out")
    assert (
        main(["batch", str(tmp_path / "a" / "chair"), str(tmp_path / "b" / "chair"), "--out", str(tmp_path / "out")])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(tmp_path / "a" / "chair") in err and str(tmp_path / "b" / "chair") in err
    assert not (tmp_path / "out").exists()


def test_an_address_that_does_not_answer_is_reported_within_seconds(tmp_path):
    port = free_port()
    start = time.perf_counter()
    with pytest.raises(
        SettingError, match=rf"address: nothing answers at 127.0.0.1:{port} within 3 s.*ray start --head --port={port}"
    ):
        check_reachable(f"127.0.0.1:{port}")
    assert time.perf_counter() - start < 4
    with socket.socket() as server:  # something listening answers
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        check_reachable(f"127.0.0.1:{server.getsockname()[1]}")


def test_the_cli_refuses_an_address_that_does_not_answer(tmp_path):
    pytest.importorskip("ray")
    start = time.perf_counter()
    address = f"127.0.0.1:{free_port()}"
    proc = run_cli("batch", tmp_path, "--out", tmp_path / "out", "--address", address, cwd=REPO, timeout=60)
    assert (
        proc.returncode == 2
        and "error: --address: nothing answers at 127.0.0.1" in proc.stderr
        and not (tmp_path / "out").exists()
    )
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert time.perf_counter() - start < 30  # imports included; the check itself is bounded by 3 s


def test_address_forms():
    assert address_endpoint("10.0.0.5:6380") == ("10.0.0.5", 6380)
    assert address_endpoint("head") == ("head", 6379)
    assert address_endpoint("ray://head") == ("head", 10001)
    assert address_endpoint("ray://head:123") == ("head", 123)
    with pytest.raises(SettingError, match="is not a number"):
        address_endpoint("head:abc")


def test_an_address_without_ray_installed_is_refused(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ConfigError, match=r"needs Ray: pip install 'matspray\[cluster\]'"):
        run_batch([tmp_path], tmp_path / "out", BatchConfig(address="127.0.0.1:6379"))


def test_failures_become_one_line_errors():
    from matspray.batch.objects import one_line
    from matspray.errors import NumericalError

    assert (
        one_line(NumericalError("refine step 3: NaN in the photometric loss"))
        == "refine step 3: NaN in the photometric loss"
    )
    oom = one_line(RuntimeError("CUDA out of memory.\nTried to allocate 2.00 GiB"))
    assert oom.startswith("out of memory (RuntimeError: CUDA out of memory. Tried") and "fewer workers" in oom
    assert one_line(MemoryError()).startswith("out of memory (MemoryError")
    assert one_line(ValueError("bad\n  value")) == "ValueError: bad value"
