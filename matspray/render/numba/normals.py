"""Each Gaussian's normal, oriented towards the camera (matspray.geometry.normals.oriented_normals, the readable
reference), in compiled loops with a hand-written backward, for backend numba. Geometry training renders the
normals beside the colour on every step; in torch they cost the whole rotation matrix of every Gaussian (some
thirty small tensor operations) and as many in autograd's backward, to keep one column of it.

    q = quats / max(|quats|, 1e-12)            (F.normalize)
    n = column k of R(q), k = argmin(log_scales)   (the shortest axis; the first index on ties, as torch.argmin)
    n = n if n . (centre - mean) >= 0 else -n  (facing the camera)

Backward: the gradient goes to the quaternion only (the axis index and the flip are choices, as argmin and
torch.where pass no gradient through them): d n / d q through the column's quadratic form, then through the
normalisation, (I - q q^T) / |q| (1 / eps where the norm was clamped).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import prange
from torch import Tensor

from matspray.render.numba.kernels import njit
from matspray.render.numba.threads import threads

CHUNK = 1024  # Gaussians per parallel iteration
NORM_EPS = 1e-12  # F.normalize's


@njit(cache=True, inline="always")
def _unit(quats, g):
    """The normalised quaternion (float64) and the norm it was divided by."""
    w, x, y, z = np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]), np.float64(quats[g, 3])
    norm = max(np.sqrt(w * w + x * x + y * y + z * z), NORM_EPS)
    return w / norm, x / norm, y / norm, z / norm, norm


@njit(cache=True, inline="always")
def _shortest(log_scales, g):
    k = 0
    if log_scales[g, 1] < log_scales[g, k]:
        k = 1
    if log_scales[g, 2] < log_scales[g, k]:
        k = 2
    return k


@njit(cache=True, inline="always")
def _column(w, x, y, z, k):
    """Column k of the rotation matrix of the unit quaternion (w, x, y, z) (matspray.gaussians.quaternion_to_matrix)."""
    if k == 0:
        return 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)
    if k == 1:
        return 2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)
    return 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True, inline="always")
def _sign(n0, n1, n2, means, centre, g):
    """+1 where the normal faces the camera (n . (centre - mean) >= 0), else -1."""
    facing = (
        n0 * (centre[0] - np.float64(means[g, 0]))
        + n1 * (centre[1] - np.float64(means[g, 1]))
        + n2 * (centre[2] - np.float64(means[g, 2]))
    )
    return 1.0 if facing >= 0.0 else -1.0


@njit(cache=True, parallel=True)
def forward(quats, log_scales, means, centre):  # [N, 4], [N, 3], [N, 3], [3] float64 -> normals [N, 3], signs [N]
    n = quats.shape[0]
    normals = np.empty((n, 3), quats.dtype)
    signs = np.empty(n, np.float64)
    for chunk in prange((n + CHUNK - 1) // CHUNK):
        for g in range(chunk * CHUNK, min(chunk * CHUNK + CHUNK, n)):
            w, x, y, z, _ = _unit(quats, g)
            n0, n1, n2 = _column(w, x, y, z, _shortest(log_scales, g))
            s = _sign(n0, n1, n2, means, centre, g)
            signs[g] = s
            normals[g, 0], normals[g, 1], normals[g, 2] = s * n0, s * n1, s * n2
    return normals, signs


@njit(cache=True, parallel=True)
def backward(quats, log_scales, signs, grad_normals):  # -> d loss / d quats [N, 4]
    n = quats.shape[0]
    grad_quats = np.empty((n, 4), quats.dtype)
    for chunk in prange((n + CHUNK - 1) // CHUNK):
        for g in range(chunk * CHUNK, min(chunk * CHUNK + CHUNK, n)):
            w, x, y, z, norm = _unit(quats, g)
            s = signs[g]
            a, b, c = s * grad_normals[g, 0], s * grad_normals[g, 1], s * grad_normals[g, 2]
            k = _shortest(log_scales, g)
            # d loss / d (w, x, y, z) of the unit quaternion: sum_i grad_i d column_k[i] / d q
            if k == 0:
                gw = 2.0 * (b * z - c * y)
                gx = 2.0 * (b * y + c * z)
                gy = 2.0 * (-2.0 * a * y + b * x - c * w)
                gz = 2.0 * (-2.0 * a * z + b * w + c * x)
            elif k == 1:
                gw = 2.0 * (-a * z + c * x)
                gx = 2.0 * (a * y - 2.0 * b * x + c * w)
                gy = 2.0 * (a * x + c * z)
                gz = 2.0 * (-a * w - 2.0 * b * z + c * y)
            else:
                gw = 2.0 * (a * y - b * x)
                gx = 2.0 * (a * z - b * w - 2.0 * c * x)
                gy = 2.0 * (a * w + b * z - 2.0 * c * y)
                gz = 2.0 * (a * x + b * y)
            if norm > NORM_EPS:  # through q / |q|: the part along q is taken out
                along = gw * w + gx * x + gy * y + gz * z
                gw, gx, gy, gz = gw - along * w, gx - along * x, gy - along * y, gz - along * z
            grad_quats[g, 0], grad_quats[g, 1] = gw / norm, gx / norm
            grad_quats[g, 2], grad_quats[g, 3] = gy / norm, gz / norm
    return grad_quats


class CompiledNormals(torch.autograd.Function):
    """(quats [N, 4], log_scales [N, 3], means [N, 3], centre [3]) -> normals [N, 3] facing the camera; the
    gradient goes to quats only."""

    @staticmethod
    def forward(ctx, quats: Tensor, log_scales: Tensor, means: Tensor, centre: Tensor) -> Tensor:
        arrays = [np.ascontiguousarray(t.detach().numpy()) for t in (quats, log_scales, means)]
        with threads():
            normals, signs = forward(*arrays, centre.detach().double().numpy())
        ctx.arrays, ctx.signs = arrays[:2], signs
        return torch.from_numpy(normals)

    @staticmethod
    def backward(ctx, grad_normals: Tensor):
        grad = np.ascontiguousarray(grad_normals.numpy(), dtype=np.float64)
        with threads():
            grad_quats = backward(*ctx.arrays, ctx.signs, grad)
        return torch.from_numpy(grad_quats), None, None, None
