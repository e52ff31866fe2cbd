"""Fixtures shared by test modules."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from matspray.device import configure_threads

ROOT = Path(__file__).resolve().parents[1]
# The tests score LPIPS with the shared test data's weights where a developer machine has them (the product never
# looks beside the repository; the benchmarks do the same in benchmarks/__init__.py)
SHARED_LPIPS = ROOT / ".." / "shared" / "data" / "lpips" / "lpips_alexnet_v0.1.npz"
if "MATSPRAY_LPIPS_WEIGHTS" not in os.environ and SHARED_LPIPS.is_file():
    os.environ["MATSPRAY_LPIPS_WEIGHTS"] = str(SHARED_LPIPS.resolve())
HOLDER = (
    "import sys, time\nfrom matspray.rundir import RunDir\nheld = RunDir(sys.argv[1]).hold()\n"
    "print('held', flush=True)\ntime.sleep(120)\n"
)


def pytest_addoption(parser):
    parser.addoption(
        "--device",
        default="cpu",
        help="where the tests marked `on_device` compute: cpu (default) or cuda "
        "(benchmarks/gpu_check.sh runs them there)",
    )


def pytest_configure(config):
    config.addinivalue_line("markers", "on_device: runs on the device given by pytest --device (the CPU by default)")
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1 and "MATSPRAY_THREADS" not in os.environ:
        # pytest -n K (make test): the cores shared among the workers, and the commands they start, not K x cores
        os.environ["MATSPRAY_THREADS"] = str(max(1, (os.cpu_count() or 1) // workers))
    configure_threads()  # $MATSPRAY_THREADS holds for the tests as for a run (one thread beside another CPU job)


@pytest.fixture
def device(request) -> torch.device:
    """The device of `pytest --device`; a test taking it runs there (a CUDA run skips where no GPU is)."""
    name = request.config.getoption("--device")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip(f"pytest --device {name}: no CUDA GPU here")
    return torch.device(name)


@pytest.fixture(autouse=True)
def test_cache(tmp_path_factory, monkeypatch):
    """Caches (undistorted images) go to a folder of the test session, not the user's ~/.cache."""
    monkeypatch.setenv("MATSPRAY_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture(scope="module")
def tiny_object(tmp_path_factory):
    """A 32 px Mitsuba sphere with 6 training and 2 test views. Where Mitsuba is missing (a GPU machine), the same
    object made elsewhere by `python -m tests.conftest DIR` and named by $MATSPRAY_TINY_OBJECT; else the test skips."""
    made = os.environ.get("MATSPRAY_TINY_OBJECT")
    if made and (Path(made) / "scene.json").is_file():
        return Path(made)
    pytest.importorskip("mitsuba")
    return make_tiny_object(tmp_path_factory.mktemp("object") / "data")


def make_tiny_object(out: Path, **settings) -> Path:
    """The tiny object made into `out`; `settings` change its SynthConfig (another seed, shape or background)."""
    from matspray.synth import SynthConfig, make_object

    tiny = dict(shape="sphere", seed=1, resolution=32, train_views=6, test_views=2, spp=4, env_height=32)
    make_object(SynthConfig(**{**tiny, **settings}), out, progress=False, notify=lambda _: None)
    return out


def run_cli(*args, timeout: float = 120, **options) -> subprocess.CompletedProcess:
    """`matspray ARGS` in a process of its own (as a user starts it), its output as text; `options` go to
    subprocess.run (cwd, env)."""
    command = [sys.executable, "-m", "matspray", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, **options)


def predict_argv(data, out, *options) -> list[str]:
    """The arguments of `matspray predict` from the dataset `data` into the run folder `out`."""
    return ["predict", "--data", str(data), "--out", str(out), *map(str, options)]


def busy_message(run, pid) -> str:
    """What a writer is told about a run folder that process `pid` holds."""
    return (
        f"{run}: another MatSpray process (pid {pid}) is writing this run folder; "
        "wait for it to finish, or use another run folder"
    )


@pytest.fixture
def hold_in_another_process():
    """hold(run) -> a process (Popen) that holds `run`'s run lock until the test ends or it is killed."""
    started = []

    def hold(run: Path) -> subprocess.Popen:
        process = subprocess.Popen(
            [sys.executable, "-c", HOLDER, str(run)], cwd=ROOT, stdout=subprocess.PIPE, text=True
        )
        started.append(process)
        assert process.stdout.readline().strip() == "held"
        return process

    yield hold
    for process in started:
        process.kill()
        process.wait()


if __name__ == "__main__":  # python -m tests.conftest DIR: the tiny object, for a machine without Mitsuba
    make_tiny_object(Path(sys.argv[1]))
