"""Who writes a run folder: `RunDir.hold` (its run.lock), re-entrant in one thread, refused or waited for elsewhere,
gone with its process; `share_stage` waits for the target's writer; the generalisation protocol trains an object's
geometry once when jobs for several models start together; the stage commands refuse a busy run folder before they
work."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import pytest

import benchmarks.generalise as generalise
from matspray.errors import RunError
from matspray.geometry.config import GeometryConfig
from matspray.method.config import build_config
from matspray.rundir import RUN_LOCK, RunDir, held_exclusively, share_stage
from tests.conftest import busy_message

ROOT = Path(__file__).resolve().parents[1]


def try_hold_in_another_process(run: Path) -> str:
    code = (
        "import sys\nfrom matspray.errors import RunError\nfrom matspray.rundir import RunDir\n"
        "try:\n    RunDir(sys.argv[1]).hold().release()\n    print('got it')\n"
        "except RunError as error:\n    print(error)\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code, str(run)], cwd=ROOT, capture_output=True, text=True, timeout=120
    ).stdout.strip()


def test_a_held_folder_is_refused_to_another_process_with_the_holders_id(tmp_path):
    run = tmp_path / "run"
    held = RunDir(run).hold()
    assert (run / RUN_LOCK).read_text().strip() == str(os.getpid())
    message = try_hold_in_another_process(run)
    assert message == busy_message(run, os.getpid())
    held.release()
    assert try_hold_in_another_process(run) == "got it"


def test_holding_again_in_one_thread_counts_up_and_the_last_release_frees_it(tmp_path):
    run = tmp_path / "run"
    first = RunDir(run).hold()
    second = RunDir(run).hold()  # a second pipeline on the folder in the same thread: no deadlock
    first.release()
    first.release()  # idempotent: releasing twice does not drop the other holder
    assert "another MatSpray process" in try_hold_in_another_process(run)
    second.release()
    assert try_hold_in_another_process(run) == "got it"


def test_the_lock_dies_with_its_process(tmp_path, hold_in_another_process):
    run = tmp_path / "run"
    holder = hold_in_another_process(run)
    with pytest.raises(RunError, match=f"pid {holder.pid}"):
        RunDir(run).hold()
    holder.send_signal(signal.SIGKILL)  # no clean-up runs: the kernel drops the lock
    holder.wait()
    RunDir(run).hold().release()


def test_waiting_blocks_until_the_holder_lets_go_and_says_so(tmp_path, hold_in_another_process):
    run = tmp_path / "run"
    holder = hold_in_another_process(run)
    heard, got = [], []
    waiter = threading.Thread(target=lambda: got.append(RunDir(run).hold(wait=True, notify=heard.append)))
    waiter.start()
    time.sleep(0.5)
    assert got == [] and heard == [f"{run}: waiting for process {holder.pid}, which is writing this run folder"]
    holder.kill()
    holder.wait()
    waiter.join(timeout=30)
    assert not waiter.is_alive() and len(got) == 1
    got[0].release()


def test_another_thread_of_one_process_is_not_the_holder(tmp_path):
    run = tmp_path / "run"
    refused = []

    def other_thread():
        with pytest.raises(RunError, match="another MatSpray process") as error:
            RunDir(run).hold()
        refused.append(error.value)

    with RunDir(run).hold():
        worker = threading.Thread(target=other_thread)
        worker.start()
        worker.join(timeout=30)
    assert len(refused) == 1


def test_share_stage_waits_while_another_process_writes_the_target(tmp_path, hold_in_another_process):
    source, target = tmp_path / "a", tmp_path / "b"
    (source / "geometry").mkdir(parents=True)
    (source / "geometry" / "gaussians.ply").write_text("points")
    (source / "geometry" / "stage.json").write_text('{"fingerprint": "f"}')
    holder = hold_in_another_process(target)
    shared = []
    job = threading.Thread(target=lambda: shared.append(share_stage(source, target, "geometry")))
    job.start()
    time.sleep(0.5)
    assert shared == [] and not (target / "geometry").exists()
    holder.kill()
    holder.wait()
    job.join(timeout=30)
    assert shared == [True] and (target / "geometry" / "gaussians.ply").read_text() == "points"


def test_jobs_for_two_models_of_one_object_train_its_geometry_once(tmp_path, monkeypatch):
    trained = []

    class GeometryPipeline:
        def __init__(self, data, out, config, **_):
            self.out = Path(out)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

        def geometry(self):
            time.sleep(0.3)  # the other job starts meanwhile
            (self.out / "geometry").mkdir(parents=True)
            record = {"fingerprint": "g", "settings": asdict(geometry.for_scene(masked=True))}
            (self.out / "geometry" / "stage.json").write_text(json.dumps(record))
            RunDir(self.out).record_timing("geometry", 1.0)
            trained.append(self.out.name)

    monkeypatch.setattr(generalise, "Pipeline", GeometryPipeline)
    runs, args, found = tmp_path / "runs", type("Args", (), {"progress": False})(), {}
    geometry = GeometryConfig(predicted_normal_weight=0.0)  # one geometry per object, shared by its models
    config = build_config("demo", **{"geometry.predicted_normal_weight": 0.0})
    assert config.geometry == geometry

    def job(model):
        found[model] = generalise.object_geometry(tmp_path / "data", runs, model, config, args, lambda _: None)

    jobs = [threading.Thread(target=job, args=(model,)) for model in ("paper", "harsh")]
    for thread in jobs:
        thread.start()
        time.sleep(0.1)
    for thread in jobs:
        thread.join(timeout=30)
    assert trained == ["paper"] and found == {"paper": runs / "paper", "harsh": runs / "paper"}


def test_held_exclusively_still_serialises_a_shared_file(tmp_path):
    order = []
    path = tmp_path / "results.json"

    def worker():
        with held_exclusively(path):
            order.append("worker")

    with held_exclusively(path):
        thread = threading.Thread(target=worker)
        thread.start()
        time.sleep(0.3)
        order.append("holder")
    thread.join(timeout=30)
    assert order == ["holder", "worker"]


def test_where_files_cannot_be_locked_it_warns_and_goes_on(tmp_path, monkeypatch):
    import fcntl

    def no_locks(handle, operation):
        raise OSError(37, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.warns(UserWarning, match="files cannot be locked here"):
        held = RunDir(tmp_path / "run").hold()
    held.release()


@pytest.mark.parametrize(
    "command",
    [
        ["geometry", "--preset", "test", "--set", "geometry.iterations=5", "--quiet"],
        ["predict", "--predictor", "simulated"],
    ],
)
def test_the_stage_commands_refuse_a_busy_run_folder_before_working(
    tiny_object, tmp_path, capsys, hold_in_another_process, command
):
    from matspray.cli import main

    run = tmp_path / "run"
    holder = hold_in_another_process(run)
    assert main([command[0], "--data", str(tiny_object), "--out", str(run), *command[1:]]) == 2
    assert capsys.readouterr().err.strip().endswith(busy_message(run, holder.pid))
    assert [p.name for p in run.iterdir()] == ["run.lock"]  # nothing predicted or trained into it
    holder.kill()
    holder.wait()
    assert main([command[0], "--data", str(tiny_object), "--out", str(run), *command[1:]]) == 0
