"""Lifting's ray response by its numba.cuda kernel (`matspray.render.rays.cuda`) against the torch version: on the
CPU in numba's CUDA simulator (a subprocess with NUMBA_ENABLE_CUDASIM=1, tiny sizes: the simulator runs each thread
in Python), on the GPU with `pytest --device cuda`. The values, and the entries lifting traces with either."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from matspray.method.lift import LiftConfig, footprint_alpha, traced_entries
from matspray.render.rays import contributions
from matspray.render.rays.contributions import _max_response, _whitened_frames
from matspray.render.rays.cuda import max_response
from matspray.render.settings import RasterSettings
from tests.test_lift_numba import dense_scene, sorted_entries

ROOT = Path(__file__).resolve().parents[1]


def response_inputs(seed: int, n: int, width: int, height: int, pairs: int, side: int, device="cpu"):
    """A dense scene's frames, random (Gaussian, pixel) candidates and a side x side sub-pixel grid."""
    gaussians, camera = dense_scene(seed, n=n, width=width, height=height)
    g = torch.Generator().manual_seed(seed)
    owner = torch.randint(0, n, (pairs,), generator=g)
    pixel_ids = torch.randint(0, width * height, (pairs,), generator=g)
    K = camera.K.double()
    offsets = (torch.arange(side, dtype=torch.float64) + 0.5) / side
    sub_y, sub_x = torch.meshgrid(offsets, offsets, indexing="ij")
    sub_x, sub_y = sub_x.reshape(-1) / K[0, 0], sub_y.reshape(-1) / K[1, 1]
    frame = tuple(x.to(device) for x in _whitened_frames(gaussians, camera))
    tensors = (gaussians.opacities.detach().double(), owner, pixel_ids)
    opacities, owner, pixel_ids = (x.to(device) for x in tensors)
    return frame, opacities, owner, pixel_ids, width, K.to(device), sub_x.to(device), sub_y.to(device)


def torch_response(*inputs) -> tuple[torch.Tensor, torch.Tensor]:
    """`_max_response` by torch operations: the reference the kernel is held to (with `FUSED` on, `_max_response`
    calls the kernel itself on a CUDA device and in the simulator)."""
    saved = contributions.FUSED[0]
    try:
        contributions.FUSED[0] = False
        return _max_response(*inputs)
    finally:
        contributions.FUSED[0] = saved


SIMULATED = """
import torch
from matspray.method.lift import LiftConfig, footprint_alpha, traced_entries
from matspray.render.rays import contributions
from matspray.render.rays import cuda as cuda_rays
from matspray.render.settings import RasterSettings
from tests.test_cuda_rays import response_inputs, torch_response
from tests.test_lift_numba import dense_scene, sorted_entries

inputs = response_inputs(0, 30, 9, 7, 40, 3)
got = cuda_rays.max_response(*inputs, 1.3)
assert got is not None, cuda_rays._STATE
expected = torch_response(*inputs, 1.3)
assert contributions.FUSED[0]
for a, b in zip(got, expected):
    torch.testing.assert_close(a, b, rtol=1e-14, atol=0)
# the entries a view gives, with the kernel (simulated) and without
gaussians, camera = dense_scene(1, n=40, width=8, height=6)
config = LiftConfig(samples_per_side=2)
core = footprint_alpha(gaussians.opacities.detach(), config, RasterSettings().max_alpha)
fused = sorted_entries(*traced_entries(gaussians, camera, None, config, RasterSettings(), core))
contributions.FUSED[0] = False
assert fused == sorted_entries(*traced_entries(gaussians, camera, None, config, RasterSettings(), core))
assert len(fused[0]) > 50
print("simulated kernel ok")
"""


def test_the_kernel_in_the_simulator_gives_the_torch_response_and_entries():
    environment = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, "-c", SIMULATED], cwd=ROOT, env=environment, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0 and "simulated kernel ok" in done.stdout, done.stderr[-3000:]


def test_without_a_simulator_or_a_gpu_the_torch_response_runs():
    # on the CPU (no simulator) `_max_response` never reaches for the kernel
    inputs = response_inputs(2, 20, 6, 5, 10, 2)
    alphas, depths = _max_response(*inputs, 1.0)
    assert alphas.shape == depths.shape == (10, 4) and alphas.dtype == torch.float64


@pytest.mark.on_device
def test_the_kernel_gives_the_torch_response_and_entries_on_the_device(device):
    if device.type != "cuda":
        pytest.skip("the kernel runs on a CUDA device (the simulator test covers it on the CPU)")
    inputs = response_inputs(3, 400, 61, 47, 5000, 16, device)
    got = max_response(*inputs, 1.0)
    assert got is not None, "the kernel did not run"
    expected = torch_response(*inputs, 1.0)
    # the same float64 arithmetic, rounded in another place where the compiler fuses a product and a sum; for a thin
    # Gaussian the whitened distance is a difference of terms of 1e5 and more, which either version knows only to
    # about 1e-11 (seen on an H200: 9e-12 relative, 2.5e-12 absolute, on 0.2 % of the values)
    torch.testing.assert_close(got[0], expected[0], rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(got[1], expected[1], rtol=1e-9, atol=1e-10)
    gaussians, camera = dense_scene(4, n=600, width=64, height=48)
    gaussians = gaussians.to(device)
    camera = camera.to(device)
    config = LiftConfig(samples_per_side=8)
    core = footprint_alpha(gaussians.opacities.detach(), config, RasterSettings().max_alpha)
    fused = sorted_entries(*traced_entries(gaussians, camera, None, config, RasterSettings(), core))
    saved = contributions.FUSED[0]
    try:
        contributions.FUSED[0] = False
        eager = sorted_entries(*traced_entries(gaussians, camera, None, config, RasterSettings(), core))
    finally:
        contributions.FUSED[0] = saved
    assert fused == eager and len(fused[0]) > 1000
