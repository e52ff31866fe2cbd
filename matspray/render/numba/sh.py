"""Spherical-harmonics colour (matspray.render.shade.sh, the readable reference) in compiled loops with a hand-written
backward, for backend numba. In geometry training the torch version is some forty small tensor operations forward
and as many in autograd's backward on every step; here it is one loop over the Gaussians each way.

rgb = max(0, sum_k c_k Y_k(d) + 0.5), d = (mean - centre) / |mean - centre|. Backward: d rgb / d c_k = Y_k(d) where
the clamp passes (torch's clamp_min passes its gradient where the input is >= the bound), and the direction's
gradient goes to the mean through the normalisation, (I - d d^T) / |mean - centre|.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import prange
from torch import Tensor

from matspray.render.numba.kernels import njit
from matspray.render.numba.threads import threads
from matspray.render.sh_constants import SH_C0, SH_C1, SH_C2, SH_C3, num_sh_bases

# the basis constants in the reference's order: C0, C1, C2[0..4], C3[0..6]
CONSTANTS = np.array([SH_C0, SH_C1, *SH_C2, *SH_C3])
CHUNK = 256  # Gaussians per parallel iteration


@njit(cache=True, inline="always")
def _direction(means, centre, n):
    vx, vy, vz = means[n, 0] - centre[0], means[n, 1] - centre[1], means[n, 2] - centre[2]
    length = max(np.sqrt(vx * vx + vy * vy + vz * vz), 1e-12)  # F.normalize's eps
    return vx / length, vy / length, vz / length, length


@njit(cache=True, inline="always")
def _basis(x, y, z, k, out):
    """out[:16] = Y_k(d) (the reference's order and signs)."""
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out[0] = k[0]
    out[1], out[2], out[3] = -k[1] * y, k[1] * z, -k[1] * x
    out[4], out[5], out[6] = k[2] * xy, k[3] * yz, k[4] * (2 * zz - xx - yy)
    out[7], out[8] = k[5] * xz, k[6] * (xx - yy)
    out[9] = k[7] * y * (3 * xx - yy)
    out[10] = k[8] * xy * z
    out[11] = k[9] * y * (4 * zz - xx - yy)
    out[12] = k[10] * z * (2 * zz - 3 * xx - 3 * yy)
    out[13] = k[11] * x * (4 * zz - xx - yy)
    out[14] = k[12] * z * (xx - yy)
    out[15] = k[13] * x * (xx - 3 * yy)


@njit(cache=True, inline="always")
def _sum(basis, sh, n, c, bases):
    """sum_b Y_b c_b of Gaussian n's colour channel c, before the offset and the clamp."""
    total = 0.0
    for b in range(bases):
        total += basis[b] * sh[n, b, c]
    return total


@njit(cache=True, parallel=True)
def forward(sh, means, centre, bases, k):  # [N, K, 3], [N, 3], [3], bases used, constants -> [N, 3]
    n_gaussians = sh.shape[0]
    rgb = np.empty((n_gaussians, 3), sh.dtype)
    for chunk in prange((n_gaussians + CHUNK - 1) // CHUNK):
        basis = np.empty(16, sh.dtype)  # once per chunk: an allocation per Gaussian costs as much as its work
        for n in range(chunk * CHUNK, min(chunk * CHUNK + CHUNK, n_gaussians)):
            x, y, z, _ = _direction(means, centre, n)
            _basis(x, y, z, k, basis)
            for c in range(3):
                rgb[n, c] = max(_sum(basis, sh, n, c, bases) + 0.5, 0.0)
    return rgb


@njit(cache=True, parallel=True)
def backward(sh, means, centre, bases, k, grad_rgb):  # -> grad sh [N, K, 3], grad means [N, 3]
    n_gaussians = sh.shape[0]
    # every element is written in the loop (zeros included): a serial np.zeros of [N, K, 3] before the parallel loop
    # would cost about as much as the loop itself
    grad_sh = np.empty(sh.shape, sh.dtype)
    grad_means = np.empty((n_gaussians, 3), sh.dtype)
    for chunk in prange((n_gaussians + CHUNK - 1) // CHUNK):
        basis = np.empty(16, sh.dtype)
        g = np.empty(16, sh.dtype)  # d loss / d Y_b
        for n in range(chunk * CHUNK, min(chunk * CHUNK + CHUNK, n_gaussians)):
            g[:] = 0.0
            x, y, z, length = _direction(means, centre, n)
            _basis(x, y, z, k, basis)
            for c in range(3):
                if _sum(basis, sh, n, c, bases) + 0.5 >= 0.0:  # where the clamp passes
                    for b in range(bases):
                        grad_sh[n, b, c] = basis[b] * grad_rgb[n, c]
                        g[b] += sh[n, b, c] * grad_rgb[n, c]
                else:
                    for b in range(bases):
                        grad_sh[n, b, c] = 0.0
                for b in range(bases, sh.shape[1]):  # bands above the degree in use
                    grad_sh[n, b, c] = 0.0
            # d loss / d direction: sum_b g_b dY_b/d(x, y, z)
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            gx = -k[1] * g[3]
            gy = -k[1] * g[1]
            gz = k[1] * g[2]
            if bases > 4:
                gx += k[2] * y * g[4] - 2 * k[4] * x * g[6] + k[5] * z * g[7] + 2 * k[6] * x * g[8]
                gy += k[2] * x * g[4] + k[3] * z * g[5] - 2 * k[4] * y * g[6] - 2 * k[6] * y * g[8]
                gz += k[3] * y * g[5] + 4 * k[4] * z * g[6] + k[5] * x * g[7]
            if bases > 9:
                gx += (
                    6 * k[7] * xy * g[9]
                    + k[8] * yz * g[10]
                    - 2 * k[9] * xy * g[11]
                    - 6 * k[10] * xz * g[12]
                    + k[11] * (4 * zz - 3 * xx - yy) * g[13]
                    + 2 * k[12] * xz * g[14]
                    + 3 * k[13] * (xx - yy) * g[15]
                )
                gy += (
                    3 * k[7] * (xx - yy) * g[9]
                    + k[8] * xz * g[10]
                    + k[9] * (4 * zz - xx - 3 * yy) * g[11]
                    - 6 * k[10] * yz * g[12]
                    - 2 * k[11] * xy * g[13]
                    - 2 * k[12] * yz * g[14]
                    - 6 * k[13] * xy * g[15]
                )
                gz += (
                    k[8] * xy * g[10]
                    + 8 * k[9] * yz * g[11]
                    + k[10] * (6 * zz - 3 * xx - 3 * yy) * g[12]
                    + 8 * k[11] * xz * g[13]
                    + k[12] * (xx - yy) * g[14]
                )
            along = gx * x + gy * y + gz * z  # the normalisation takes out the part along d
            grad_means[n, 0] = (gx - along * x) / length
            grad_means[n, 1] = (gy - along * y) / length
            grad_means[n, 2] = (gz - along * z) / length
    return grad_sh, grad_means


class CompiledSH(torch.autograd.Function):
    """(sh [N, K, 3], means [N, 3], centre [3], degree) -> rgb [N, 3], as `sh.sh_to_rgb(sh, view_directions(means))`."""

    @staticmethod
    def forward(ctx, sh: Tensor, means: Tensor, centre: Tensor, degree: int) -> Tensor:
        arrays = [np.ascontiguousarray(t.detach().numpy()) for t in (sh, means, centre.to(means.dtype))]
        ctx.arrays, ctx.bases = arrays, num_sh_bases(degree)
        with threads():
            rgb = forward(*arrays, ctx.bases, CONSTANTS.astype(arrays[0].dtype))
        return torch.from_numpy(rgb)

    @staticmethod
    def backward(ctx, grad_rgb: Tensor):
        grad = np.ascontiguousarray(grad_rgb.numpy(), dtype=ctx.arrays[0].dtype)
        with threads():
            grad_sh, grad_means = backward(*ctx.arrays, ctx.bases, CONSTANTS.astype(grad.dtype), grad)
        return torch.from_numpy(grad_sh), torch.from_numpy(grad_means), None, None
