"""Backend gsplat: how it is chosen (every branch of resolve_backend, the CUDA build check, the CLI's one-line
refusal). gsplat's rasterization against backend torch is tests/test_gsplat_parity.py."""

from __future__ import annotations

import types

import pytest
import torch
import yaml

from matspray.errors import SettingError
from matspray.method.config import PipelineConfig
from matspray.render import backend as backend_module
from matspray.render.backend import gsplat_cuda_error, gsplat_import_error, resolve_backend
from matspray.rundir import RunDir
from tests import gsplat_cpu
from tests.conftest import run_cli
from tests.gsplat_cpu import gsplat_on_cpu


@pytest.fixture(autouse=True)
def fresh_backend_checks(monkeypatch):
    """Each test starts with nothing checked or told yet in this process."""
    monkeypatch.setattr(backend_module, "_CHECKED", {})
    monkeypatch.setattr(backend_module, "_TOLD", set())


def block_gsplat(monkeypatch):
    real_import = backend_module.importlib.import_module

    def fake_import(name, *args):
        if name.split(".")[0] == "gsplat":
            raise ImportError("No module named 'gsplat'")
        return real_import(name, *args)

    monkeypatch.setattr(backend_module.importlib, "import_module", fake_import)


def fake_cuda(monkeypatch, cuda_error=None, calls=None):
    """torch says CUDA is there; gsplat imports, and its CUDA check answers `cuda_error` (counted in `calls`)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(backend_module, "gsplat_import_error", lambda: None)

    def check(device, notify=None):
        if calls is not None:
            calls.append(str(device))
        return cuda_error

    monkeypatch.setattr(backend_module, "gsplat_cuda_error", check)


# ---------------------------------------------------------------- choosing the backend


def test_unknown_backend_names_the_setting():
    with pytest.raises(
        SettingError, match="backend: unknown backend 'optix'; choose one of auto, torch, numba, gsplat"
    ):
        resolve_backend("optix", "cpu")
    with pytest.raises(SettingError, match="backend: unknown backend"):
        PipelineConfig(backend="optix")


def test_config_yaml_records_the_backend(tmp_path):
    RunDir(tmp_path).write_config(PipelineConfig(backend="torch"))
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["backend"] == "torch"


def test_torch_is_always_available():
    assert resolve_backend("torch", "cpu") == "torch"
    assert resolve_backend("torch", "cuda") == "torch"


def test_auto_on_cpu_is_numba_without_a_word(monkeypatch):
    told = []
    monkeypatch.setattr(backend_module, "gsplat_import_error", lambda: None)
    assert (
        resolve_backend("auto", "cpu", notify=told.append) == "numba"
    )  # the compiled CPU rasterizer (a core dependency)
    assert told == []


def test_auto_on_cuda_takes_gsplat_when_its_extension_runs(monkeypatch):
    calls = []
    fake_cuda(monkeypatch, None, calls)
    assert resolve_backend("auto", "cuda") == "gsplat"
    assert (
        resolve_backend("auto", "cuda:0") == "gsplat" and resolve_backend("gsplat", torch.device("cuda", 0)) == "gsplat"
    )
    assert calls == ["cuda"]  # checked once per process


def test_auto_on_cuda_falls_back_with_one_line_once(monkeypatch):
    calls, told = [], []
    fake_cuda(monkeypatch, "RuntimeError: Error building extension 'gsplat_cuda'", calls)
    for _ in range(3):
        assert resolve_backend("auto", "cuda", notify=told.append) == "torch"
    assert calls == ["cuda"]
    assert len(told) == 1 and "\n" not in told[0]
    assert told[0].startswith(
        "backend auto: rendering with torch; gsplat's CUDA extension does not build or run "
        "(RuntimeError: Error building extension 'gsplat_cuda'); gsplat compiles its CUDA code with nvcc"
    )


def test_auto_on_cuda_without_gsplat_says_how_to_install(monkeypatch):
    told = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    block_gsplat(monkeypatch)
    assert resolve_backend("auto", "cuda", notify=told.append) == "torch"
    assert len(told) == 1 and "gsplat is not installed" in told[0] and "pip install 'matspray[cuda]'" in told[0]


def test_gsplat_without_cuda_says_so(monkeypatch):
    monkeypatch.setattr(backend_module, "gsplat_import_error", lambda: None)
    with pytest.raises(SettingError, match="backend: gsplat needs a CUDA device.*use backend torch"):
        resolve_backend("gsplat", "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SettingError, match="needs a CUDA device"):
        resolve_backend("gsplat", "cuda")


def test_gsplat_not_installed_says_how_to_install(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    block_gsplat(monkeypatch)
    assert "No module named 'gsplat'" in gsplat_import_error()
    with pytest.raises(
        SettingError, match=r"gsplat is not installed.*pip install 'matspray\[cuda\]' \(needs nvcc and ninja"
    ) as error:
        resolve_backend("gsplat", "cuda")
    assert "\n" not in str(error.value)


def test_gsplat_with_a_failed_build_says_what_to_install(monkeypatch):
    fake_cuda(monkeypatch, "RuntimeError: Error building extension 'gsplat_cuda'")
    with pytest.raises(
        SettingError,
        match=r"backend: gsplat's CUDA extension does not build or run \(RuntimeError: Error building "
        r"extension 'gsplat_cuda'\); .*CUDA toolkit .*ninja",
    ) as error:
        resolve_backend("gsplat", "cuda")
    assert "\n" not in str(error.value)


def fake_extension(monkeypatch, compiled, seconds: float = 0.0):
    """gsplat.cuda._backend as gsplat leaves it: `_C` the compiled module (None: it found no nvcc); importing it
    'takes' `seconds`, or raises `compiled` when that is an exception (a failed build)."""
    real_import = backend_module.importlib.import_module
    clock = [100.0 + seconds, 100.0]  # popped: the start, then every later reading

    def fake_import(name, *args):
        if name == "gsplat.cuda._backend":
            if isinstance(compiled, Exception):
                raise compiled
            return types.SimpleNamespace(_C=compiled)
        return real_import(name, *args)

    monkeypatch.setattr(backend_module.importlib, "import_module", fake_import)
    monkeypatch.setattr(backend_module, "perf_counter", lambda: clock.pop() if len(clock) > 1 else clock[0])


def test_cuda_check_renders_one_gaussian_and_says_how_long_the_build_took(monkeypatch):
    gsplat_on_cpu(monkeypatch)  # the check's test render goes through gsplat's Python code, on the CPU
    fake_extension(monkeypatch, object(), seconds=187.25)
    told = []
    assert gsplat_cuda_error("cpu", notify=told.append) is None
    assert told == [
        "gsplat: CUDA extension ready in 187.2 s (compiled at its first use, reused from the build cache after that)"
    ]


def test_cuda_check_reports_a_failed_build_in_one_line(monkeypatch):
    fake_extension(
        monkeypatch, RuntimeError("Error building extension 'gsplat_cuda'\nninja: build stopped: subcommand failed.")
    )
    told = []
    assert gsplat_cuda_error("cpu", notify=told.append) == "RuntimeError: Error building extension 'gsplat_cuda'"
    assert told == []


def test_cuda_check_reports_a_missing_toolkit(monkeypatch):
    fake_extension(monkeypatch, None)
    assert gsplat_cuda_error("cpu") == "gsplat found no CUDA toolkit (nvcc) to compile its CUDA code with"


def test_cuda_check_catches_a_wrong_render(monkeypatch):
    gsplat_on_cpu(monkeypatch)
    fake_extension(monkeypatch, object())
    monkeypatch.setattr(gsplat_cpu, "MAX_ALPHA", 0.2)  # kernels that clamp every alpha to 0.2
    assert "rendered a test Gaussian wrongly (alpha 0.200" in gsplat_cuda_error("cpu")


def test_harness_makes_gsplat_resolve_on_cpu(monkeypatch):
    gsplat_on_cpu(monkeypatch)
    assert resolve_backend("gsplat", "cpu") == "gsplat" and resolve_backend("auto", "cpu") == "gsplat"


def test_cli_backend_gsplat_on_cpu_is_one_line(tmp_path):
    run = ("run", "--data", tmp_path / "nowhere", "--out", tmp_path / "run", "--preset", "test")
    result = run_cli(*run, "--device", "cpu", "--backend", "gsplat")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--backend" in lines[0] and "gsplat" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()
