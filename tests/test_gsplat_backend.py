"""Backend selection (CPU: every branch of resolve_backend, the CLI's one-line refusal) and, where CUDA
and gsplat are present, parity of the gsplat backend with ours on small scenes."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
import yaml

from matspray.config import PipelineConfig
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.render import backend as backend_module
from matspray.render.backend import BACKENDS, gsplat_import_error, resolve_backend
from matspray.render.rasterize import rasterize
from matspray.rundir import RunDir
from tests.test_rasterize import random_scene


def block_gsplat(monkeypatch):
    real_import = backend_module.importlib.import_module

    def fake_import(name, *args):
        if name.split(".")[0] == "gsplat":
            raise ImportError("No module named 'gsplat'")
        return real_import(name, *args)

    monkeypatch.setattr(backend_module.importlib, "import_module", fake_import)


def fake_gsplat_present(monkeypatch):
    monkeypatch.setattr(backend_module, "gsplat_import_error", lambda: None)


def test_backends_are_the_cli_choices():
    assert BACKENDS == ("auto", "torch", "gsplat")


def test_unknown_backend_names_the_setting():
    with pytest.raises(SettingError, match="backend: unknown backend 'optix'; choose one of auto, torch, gsplat"):
        resolve_backend("optix", "cpu")
    with pytest.raises(SettingError, match="backend: unknown backend"):
        PipelineConfig(backend="optix")


def test_config_yaml_records_the_backend(tmp_path):
    RunDir(tmp_path).write_config(PipelineConfig(backend="torch"))
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["backend"] == "torch"


def test_torch_is_always_available():
    assert resolve_backend("torch", "cpu") == "torch"
    assert resolve_backend("torch", "cuda") == "torch"


def test_auto_on_cpu_is_torch_even_with_gsplat(monkeypatch):
    fake_gsplat_present(monkeypatch)
    assert resolve_backend("auto", "cpu") == "torch"


def test_auto_on_cuda_depends_on_gsplat(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    fake_gsplat_present(monkeypatch)
    assert resolve_backend("auto", "cuda") == "gsplat"
    block_gsplat(monkeypatch)
    monkeypatch.setattr(backend_module, "gsplat_import_error", gsplat_import_error)
    assert resolve_backend("auto", "cuda") == "torch"


def test_gsplat_without_cuda_says_so(monkeypatch):
    fake_gsplat_present(monkeypatch)
    with pytest.raises(SettingError, match="backend: gsplat needs a CUDA device.*use --backend torch"):
        resolve_backend("gsplat", "cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SettingError, match="needs a CUDA device"):
        resolve_backend("gsplat", "cuda")


def test_gsplat_not_installed_says_how_to_install(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    block_gsplat(monkeypatch)
    assert "No module named 'gsplat'" in gsplat_import_error()
    with pytest.raises(SettingError, match=r"gsplat is not installed.*pip install 'matspray\[cuda\]' \(needs nvcc and ninja"):
        resolve_backend("gsplat", "cuda")


def test_rasterize_default_backend_is_torch_and_auto_on_cpu_matches_it():
    gaussians, camera, features = random_scene(12, 3)
    a = rasterize(gaussians, camera, features)
    b = rasterize(gaussians, camera, features, backend="auto")
    torch.testing.assert_close(a.features, b.features)
    torch.testing.assert_close(a.alpha, b.alpha)


def test_cli_backend_gsplat_on_cpu_is_one_line(tmp_path):
    result = subprocess.run([sys.executable, "-m", "matspray", "run", "--data", tmp_path / "nowhere", "--out", tmp_path / "run",
                             "--preset", "test", "--device", "cpu", "--backend", "gsplat"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "--backend" in lines[0] and "gsplat" in lines[0], result.stderr
    assert not (tmp_path / "run").exists()


def gsplat_missing_reason() -> str | None:
    if not torch.cuda.is_available():
        return "no CUDA device here (the gsplat backend is CUDA only)"
    error = gsplat_import_error()
    return None if error is None else f"gsplat does not import ({error}); pip install 'matspray[cuda]'"


needs_gsplat = pytest.mark.skipif(gsplat_missing_reason() is not None, reason=str(gsplat_missing_reason()))


def to_cuda(gaussians: Gaussians, camera, features):
    leaves = [t.detach().cuda().requires_grad_(True) for t in (gaussians.means, gaussians.log_scales, gaussians.quats,
                                                               gaussians.opacity_logits)]
    return Gaussians(*leaves, gaussians.sh.cuda()), camera.to("cuda"), features.detach().cuda().requires_grad_(True)


@needs_gsplat
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gsplat_matches_torch(seed):
    # tolerances: both backends blend the same hits in float32; gsplat sorts by tile and by the depth of the
    # centre like ours, so images agree to rounding except where a hit sits on the 1/255 alpha threshold
    gaussians, camera, features = random_scene(40, seed, width=24, height=20)
    results = []
    for backend in ("torch", "gsplat"):
        g, cam, f = to_cuda(gaussians, camera, features)
        out = rasterize(g, cam, f, torch.linspace(0.1, 0.7, f.shape[1], device="cuda"), backend=backend)
        loss = (out.features * torch.linspace(0.5, 1.5, f.shape[1], device="cuda")).sum() + out.alpha.sum() + 0.1 * out.depth.sum()
        loss.backward()
        results.append((out, g, f))
    (a, ga, fa), (b, gb, fb) = results
    torch.testing.assert_close(b.features, a.features, atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(b.alpha, a.alpha, atol=2e-3, rtol=1e-3)
    torch.testing.assert_close(b.depth, a.depth, atol=1e-2, rtol=1e-3)
    for x, y in ((ga.means, gb.means), (ga.opacity_logits, gb.opacity_logits), (fa, fb)):
        torch.testing.assert_close(y.grad, x.grad, atol=2e-2, rtol=2e-2)
