"""One device and one backend per run: what each stage really ran on, no tensor made on the wrong device, running
out of memory, the frozen views' storage. Tests taking the `device` fixture run where `pytest --device` says."""

from __future__ import annotations

import json

import pytest
import torch

from matspray.cli import main
from matspray.device import out_of_memory_as_error, resolve_device
from matspray.errors import ResourceError, SettingError
from matspray.eval.run_eval import evaluate_run
from matspray.method.config import build_config, shadow_maps
from matspray.method.pipeline import Pipeline
from matspray.method.relight import render_relit
from matspray.presets import VARIANT_NAMES
from matspray.render.backend import gsplat_device_error, rendering_with
from matspray.render.raster.gbuffer import FrozenViews, frozen_views_bytes
from matspray.render.raster.reference import splat_pixels
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.latlong import pixel_solid_angles
from tests.stray_tensors import stray_tensor_check
from tests.test_rasterize import random_scene

pytestmark = pytest.mark.on_device


def run_config(device, **settings):
    # with baked shadows (off by default), so that every stage runs
    return build_config(
        "test",
        predictor="simulated",
        **{
            "device": str(device),
            "backend": "torch",
            "refine.iterations": 8,
            "visibility": shadow_maps("test"),
            **settings,
        },
    )


def stage_record(run, stage: str) -> dict:
    return json.loads((run / stage / "stage.json").read_text())


def test_every_stage_records_its_device_and_what_it_rendered_with(tiny_object, tmp_path, device):
    # what auto picks: on a GPU the real gsplat (torch where it cannot run), on the CPU numba
    backend = "numba" if device.type == "cpu" else "gsplat" if gsplat_device_error(device) is None else "torch"
    config = run_config(device, backend=backend)
    with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lambda _: None) as pipeline:
        pipeline.refine("full")
    run = tmp_path / "run"
    for stage in ("geometry", "lift", "visibility", "asset"):
        record = stage_record(run, stage)
        assert record["device"] == str(device) and record["backend"] == backend, stage
    geometry = stage_record(run, "geometry")["renders"]
    assert set(geometry) == {backend} and geometry[backend] >= 60  # 60 steps of the test preset, then the test views
    rays = "rays-numba" if backend == "numba" else "rays"  # lifting's tracer: compiled where the run renders with numba
    assert stage_record(run, "lift")["renders"] == {rays: 6}  # one ray-traced view per training view
    assert stage_record(run, "visibility")["renders"] == {
        "torch": 2 * shadow_maps("test").rows ** 2
    }  # the shadow maps: torch's weights
    frozen = stage_record(run, "asset")["frozen_views"]
    assert (
        frozen["backend"] == backend and frozen["views"] == 6 and (frozen["bytes"] > 0) == (backend != "gsplat")
    )  # numba keeps torch's matrices


def test_no_tensor_is_made_without_its_device(tiny_object, tmp_path, device):
    """Every stage, evaluation and relighting, under the stray-tensor check (see tests/stray_tensors.py)."""
    config = run_config(device)
    with stray_tensor_check() as strays:
        with Pipeline(tiny_object, tmp_path / "run", config, progress=False, log=lambda _: None) as pipeline:
            assets = pipeline.run_all(VARIANT_NAMES)
        evaluate_run(tmp_path / "run", progress=False, device=device, backend="torch")
        light = EnvironmentMap.constant(0.5, height=8, device=device).prefilter()
        with rendering_with("torch"):
            rgb, alpha = render_relit(assets["full"], pipeline.scene.test[0].camera.to(device), light)
    assert strays == []
    assert rgb.device.type == device.type and torch.isfinite(rgb).all() and alpha.max() > 0.5


def test_the_stray_check_catches_a_tensor_made_without_a_device():
    generator = torch.Generator().manual_seed(0)
    with stray_tensor_check() as strays:
        made = pixel_solid_angles(4, 8)  # device=None: the default device
        drawn = torch.rand(3, generator=generator)  # an explicit CPU generator: on the CPU on purpose
        kept = torch.as_tensor(torch.ones(2, device="cpu"))
    assert made.device.type == "meta" and drawn.device.type == "cpu" and kept.device.type == "cpu"
    assert len(strays) == 1 and strays[0].startswith("render/shade/latlong.py:"), strays


def test_out_of_memory_is_one_line_and_the_run_resumes(tiny_object, tmp_path, monkeypatch):
    run = tmp_path / "run"
    config = run_config("cpu", visibility=None)

    def out_of_memory(*args, **kwargs):
        raise torch.OutOfMemoryError(
            "CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 23.6 GiB"
        )

    monkeypatch.setattr("matspray.method.stages.lift", out_of_memory)
    with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
        with pytest.raises(ResourceError) as raised:
            pipeline.refine("full")
    message = str(raised.value)
    assert message.startswith("lift: out of memory on cpu allocating 2.00 GiB; lower the image size (--downscale 2)")
    assert "\n" not in message and "(finished stages are reused)" in message
    assert not (run / "lift").exists()  # nothing half-written
    geometry_record = (run / "geometry" / "stage.json").read_text()
    monkeypatch.undo()
    with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
        pipeline.refine("full")
    assert (run / "lift" / "projected.pt").exists() and (run / "asset" / "asset.ply").exists()
    assert (run / "geometry" / "stage.json").read_text() == geometry_record  # geometry was reused, not trained again


def test_host_memory_running_out_is_one_line_and_other_errors_pass_through():
    with pytest.raises(ResourceError, match=r"^export: out of host memory allocating 8589934592 bytes; lower"):
        with out_of_memory_as_error("export", "cpu"):
            raise RuntimeError(
                "[enforce fail at alloc_cpu.cpp:118] DefaultCPUAllocator: can't allocate memory: "
                "you tried to allocate 8589934592 bytes"
            )
    with pytest.raises(RuntimeError, match="something else"):
        with out_of_memory_as_error("export", "cpu"):
            raise RuntimeError("something else")


def test_cuda_without_cuda_is_one_line_that_says_what_to_do(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(
        SettingError,
        match=r"^device: cuda: this (torch build has no CUDA|machine has no CUDA GPU that torch sees); "
        r"use cpu, or a CUDA build of torch on a machine with an NVIDIA GPU$",
    ):
        resolve_device("cuda")
    with pytest.raises(SettingError, match="unsupported device 'mps'"):
        resolve_device("mps")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("command", ["geometry", "relight", "eval", "export"])
def test_every_computing_command_refuses_cuda_without_it_in_one_line(tmp_path, command, capsys):
    """The command's own `main`, in this process (a traceback would be an exception here)."""
    arguments = {
        "geometry": ["--data", tmp_path, "--out", tmp_path / "run"],
        "relight": ["--run", tmp_path, "--env", "studio", "--out", tmp_path / "o"],
        "eval": ["--run", tmp_path],
        "export": ["--run", tmp_path, "--out", tmp_path / "a.glb"],
    }[command]
    status = main([command, *map(str, arguments), "--device", "cuda"])
    stderr = capsys.readouterr().err
    lines = stderr.strip().splitlines()
    assert status == 2 and len(lines) == 1, stderr
    assert "--device: cuda: this" in lines[0] and "no CUDA" in lines[0] and "use cpu" in lines[0], stderr


def frozen_render(storage: str, features: torch.Tensor, device: torch.device):
    gaussians, camera, _ = random_scene(30, 4, width=20, height=16)
    frozen = FrozenViews(gaussians.to(device), [camera.to(device)] * 2, backend="torch", storage=storage)
    features = features.to(device).clone().requires_grad_(True)
    image, alpha = frozen.render(1, features)
    (image * torch.linspace(0.5, 1.5, image.shape[-1], device=device)).sum().backward()
    return frozen, image.detach(), alpha, features.grad


def test_frozen_views_kept_on_the_host_render_and_differentiate_as_the_reference(device):
    """The frozen views on `device` (pytest --device; gpu_check.sh runs this on CUDA) with their blend matrices kept
    beside the Gaussians ("device") or in host memory ("host", pinned wherever CUDA is there to pin for), against
    the per-pixel reference: each pixel's blending weights from `splat_pixels` in float64 (one feature channel per
    Gaussian), the image their product with the features and the features' gradient the transposed product."""
    features = torch.rand(30, 4, generator=torch.Generator().manual_seed(1))
    gaussians, camera, _ = random_scene(30, 4, width=20, height=16)
    weights = splat_pixels(gaussians, camera, torch.eye(30, dtype=torch.float64))[0].reshape(16 * 20, 30)
    upstream = torch.linspace(0.5, 1.5, 4, dtype=torch.float64).expand(16 * 20, 4)
    expected_image = (weights @ features.double()).reshape(16, 20, 4)
    expected_alpha, expected_grad = weights.sum(-1).reshape(16, 20), weights.T @ upstream
    assert expected_alpha.max() > 0.9 and (expected_alpha < 0.1).any()  # covered and open pixels both
    results = {}
    for storage in ("device", "host"):
        frozen, image, alpha, grad = results[storage] = frozen_render(storage, features, device)
        on_host = storage == "host"
        assert frozen.on_host == [on_host, on_host]
        # the transposes are kept for CUDA's products only: the CPU's matrices are packed (numpy arrays, 16-bit
        # weights) and its backward pass scatters through them
        assert all((t is None) == (device.type == "cpu") for t in frozen.transposed)
        for matrix in [m for m in frozen.matrices + frozen.transposed if isinstance(m, torch.Tensor)]:
            assert matrix.device.type == ("cpu" if on_host else device.type)
            assert matrix.values().is_pinned() == (on_host and torch.cuda.is_available())  # pinned where CUDA is
        assert all(isinstance(m, torch.Tensor) == (device.type != "cpu") for m in frozen.matrices)
        assert image.device.type == alpha.device.type == grad.device.type == device.type
        steps = 30 * 0.5 / 65535 if device.type == "cpu" else 0.0  # up to 30 packed weights in a sum
        torch.testing.assert_close(image.cpu().double(), expected_image, rtol=0, atol=1e-5 + steps)
        torch.testing.assert_close(alpha.cpu().double(), expected_alpha, rtol=0, atol=1e-5 + steps)
        torch.testing.assert_close(grad.cpu().double(), expected_grad, rtol=0, atol=1e-4 + 20 * steps)
    (on_device, image, alpha, grad), (_, host_image, host_alpha, host_grad) = results["device"], results["host"]
    # the same matrices, wherever they are kept: the same values, but for the order of the sums, which CUDA's sparse
    # products may change from one call to the next (one float32 rounding seen on an H200)
    exact = dict(rtol=0, atol=0) if device.type == "cpu" else dict(rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(host_image, image, **exact)
    torch.testing.assert_close(host_alpha, alpha, **exact)
    torch.testing.assert_close(host_grad, grad, **exact)
    described = on_device.describe()
    transposed = device.type != "cpu"
    assert described["transposed"] == transposed
    assert (
        described["bytes"] == on_device.kept_bytes == frozen_views_bytes(described["hits"], 20 * 16, 30, 2, transposed)
    )
    assert described["hits"] > 0 and described["pixels"] == 2 * 20 * 16
    assert described["views_on_host"] == 0 and results["host"][0].describe()["views_on_host"] == 2


def test_auto_storage_moves_views_to_the_host_when_the_gpu_runs_short(monkeypatch):
    free = iter([10, 9, 1])  # bytes free of 10: the third view finds less than a quarter left
    monkeypatch.setattr("matspray.render.raster.gbuffer._room_on", lambda device: next(free) >= 0.25 * 10)
    gaussians, camera, _ = random_scene(30, 4, width=20, height=16)
    frozen = FrozenViews(gaussians, [camera] * 3, backend="torch", storage="auto")
    assert frozen.on_host == [False, False, True]


def test_a_run_forced_to_gsplat_renders_every_stage_with_it(tiny_object, tmp_path, monkeypatch):
    """gsplat's own rasterization() through the CPU harness: every rasterizing stage calls it, none falls back."""
    pytest.importorskip("gsplat")
    from matspray.export.surface import render_depths
    from matspray.method.masks import compute_object_masks
    from tests.gsplat_cpu import gsplat_on_cpu

    gsplat_on_cpu(monkeypatch)
    run = tmp_path / "run"
    config = run_config(
        "cpu", backend="gsplat", visibility=None, **{"geometry.absgrad": True, "geometry.grad_threshold": 8e-4}
    )
    with Pipeline(tiny_object, run, config, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.backend == "gsplat"
        asset = pipeline.refine("full")
        gaussians, _ = pipeline.geometry()
        cameras = [v.camera for v in pipeline.scene.train]
        with rendering_with(pipeline.backend) as use:
            masks = compute_object_masks(gaussians, pipeline.scene, (0.0, 0.0, 0.0, 2.0), progress=False)
            evaluate_run(run, progress=False, device=pipeline.device, backend=pipeline.backend)
            rgb, alpha = render_relit(asset, cameras[0], EnvironmentMap.constant(0.5, height=8).prefilter())
            depths = render_depths(asset.gaussians, cameras)
    for stage in ("geometry", "lift", "asset"):
        assert stage_record(run, stage)["backend"] == "gsplat", stage
    geometry = stage_record(run, "geometry")
    assert set(geometry["renders"]) == {"gsplat"} and geometry["renders"]["gsplat"] >= 60
    assert stage_record(run, "lift")["renders"] == {"rays": 6}  # lifting traces rays with our code on every backend
    refined = stage_record(run, "asset")
    assert (
        set(refined["renders"]) == {"gsplat"}
        and refined["frozen_views"]["backend"] == "gsplat"
        and refined["frozen_views"]["bytes"] == 0
    )
    # the object masks (8 views), evaluation (2 test views), relighting (1) and the export's depth maps (6)
    assert set(use.used()) == {"gsplat"} and use.calls["gsplat"] >= 8 + 2 + 1 + 6
    assert len(masks.masks["train"]) == 6 and all(m.max() > 0.5 for m in masks.masks["train"].values())
    assert alpha.max() > 0.5 and torch.isfinite(rgb).all() and all(d.max() > 0 for d, _ in depths)
