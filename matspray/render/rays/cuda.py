"""Lifting's ray response (`contributions._max_response`, eq. 1-2) as one numba.cuda kernel on a CUDA device.

The torch version evaluates a candidate (Gaussian, pixel) pair's k x k sub-pixel rays as about thirty float64
operations over [P, k^2] tensors: each one a kernel that reads and writes the whole band (at 16 x 16 rays, hundreds
of megabytes each). The kernel computes a ray's alpha_max and tau_max in registers from the pair's Gaussian frame
and writes only those two: the same float64 arithmetic in the same order, one pass over the band.

Bit for bit it can differ from torch's separate kernels where the compiler fuses a product and a sum into one
rounding (numba's `fastmath=False` leaves contraction to NVVM's default); a hit whose alpha lies within a rounding of
min_alpha can then flip. tests/test_cuda_rays.py checks the values against the torch version (in numba's CUDA
simulator on the CPU, on the GPU with `pytest --device cuda`) and the entries lifting traces with either.

`max_response(...)` returns None where the kernel cannot run (numba.cuda missing, no driver, a failed compile):
the caller computes the response with torch then, and the reason is said once.
"""

from __future__ import annotations

import os
import sys

import torch
from torch import Tensor

THREADS = 256
_STATE: dict = {}  # "kernel": the compiled kernel, or "off": why it cannot run


def _kernel():
    """The compiled kernel (`cuda_rays_kernel`, whose import brings numba.cuda: only where a GPU traces a band)."""
    if "kernel" not in _STATE:
        from matspray.render.rays.cuda_kernel import response

        _STATE["kernel"] = response
    return _STATE["kernel"]


def simulated() -> bool:
    """Whether numba runs CUDA kernels in its simulator on the CPU (NUMBA_ENABLE_CUDASIM=1: tests at tiny sizes)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"


def _array(tensor: Tensor):
    """What the kernel reads or writes: the tensor's own device memory (numba's view of it, no copy) on a GPU; in
    numba's CUDA simulator (tests on the CPU) its numpy view, which the simulator writes through."""
    from numba import cuda

    # sync=False: the kernel is launched on torch's stream, behind the work that made the tensor; numba's default
    # would wait on the host for that stream first
    return cuda.as_cuda_array(tensor, sync=False) if tensor.is_cuda else tensor.numpy()


def max_response(
    frame: tuple[Tensor, Tensor],  # A [N, 3, 3], origin [N, 3] float64 (`contributions._whitened_frames`)
    opacities: Tensor,  # [N] float64
    owner: Tensor,  # [P] long
    pixel_ids: Tensor,  # [P] long
    width: int,
    K: Tensor,  # [3, 3] float64
    sub_x: Tensor,  # [S] float64
    sub_y: Tensor,  # [S]
    falloff: float,
) -> tuple[Tensor, Tensor] | None:  # alpha_max [P, S], camera z of x_max [P, S]; None: compute them with torch
    """`contributions._max_response` by the kernel, or None where it cannot run (said once)."""
    if "off" in _STATE:
        return None
    try:
        from numba import cuda

        kernel = _kernel()
        count, samples = owner.numel(), sub_x.numel()
        alphas = torch.empty(count, samples, dtype=torch.float64, device=owner.device)
        depths = torch.empty_like(alphas)
        if count == 0:
            return alphas, depths
        k = torch.stack([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]).contiguous()  # fx, fy, cx, cy
        args = [frame[0].contiguous(), frame[1].contiguous(), opacities.contiguous(), owner.contiguous()]
        args += [pixel_ids.contiguous(), width, k, sub_x.contiguous(), sub_y.contiguous(), -0.5 * falloff]
        args += [alphas, depths]
        args = [_array(x) if isinstance(x, Tensor) else x for x in args]
        blocks = (count * samples + THREADS - 1) // THREADS
        if owner.is_cuda:  # on torch's stream, so it runs in order with the kernels around it
            stream = cuda.external_stream(torch.cuda.current_stream(owner.device).cuda_stream)
            kernel[blocks, THREADS, stream](*args)
        else:
            kernel[blocks, THREADS](*args)
        return alphas, depths
    except Exception as exc:  # no numba.cuda, no driver, no NVVM: torch computes the same response
        why = f"{type(exc).__name__}: {(str(exc).strip().splitlines() or [''])[0]}"
        print(f"lifting traces rays without its CUDA kernel ({why})", file=sys.stderr)
        _STATE["off"] = why
        return None
