"""Frozen views' blend matrices on the CPU (matspray.render.raster.gbuffer): each view's blending weights as a packed
CSR matrix [pixels, Gaussians], its product with the features and, for the backward pass, the product of its
transpose with the image's gradient, without keeping that transpose.

Packed: a column (Gaussian) index takes 16 bits where the Gaussians number at most 2^16 (32 beyond), and a weight,
which lies in [0, 1], is kept as round(weight * WEIGHT_STEPS) in 16 bits, within 0.5 / WEIGHT_STEPS (7.6e-6) of
itself: 4 bytes per (Gaussian, pixel) weight instead of torch CSR's 8, and 16 with the transpose
(docs/dev/real-captures.md, "Frozen views without their transposes" and "Packed frozen views").

The product is a gather, row by row. The transposed product cuts the rows into chunks of about CHUNK_HITS weights;
each chunk scatters its rows into a [N, C] buffer of its own (chunks run in parallel), and the buffers are summed in
chunk order. Both depend on the matrix only, so their results have the same bits whatever the thread count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import prange
from torch import Tensor

from matspray.render.numba.kernels import call_saying_compiled, njit
from matspray.render.numba.threads import threads

CHUNK_HITS = 1 << 18  # weights per chunk: a chunk's [N, C] buffer costs about as much as scattering them
MAX_CHUNKS = 16  # at most this many [N, C] buffers at once
WEIGHT_STEPS = 65535  # a weight w in [0, 1] is kept as the 16-bit integer round(w * WEIGHT_STEPS)
SHORT_COLUMNS = 2**16  # up to this many columns (Gaussians) a column index takes 16 bits, 32 beyond


@dataclass(frozen=True, eq=False)
class PackedBlend:
    """A view's blend matrix [rows, columns] (pixels, Gaussians): CSR row pointers `crow` [rows + 1] (int32, or
    int64 for 2^31 weights or more), column indices `col` [M] (uint16, or int32 for more than 2^16 columns) and
    weights `steps` [M] (uint16, the weight times WEIGHT_STEPS). `matrix @ features` is its product."""

    crow: np.ndarray
    col: np.ndarray
    steps: np.ndarray
    shape: tuple[int, int]

    @property
    def nbytes(self) -> int:
        return self.crow.nbytes + self.col.nbytes + self.steps.nbytes

    def __matmul__(self, features: Tensor) -> Tensor:  # [N, C] -> [P, C], in features' float type
        features = features.contiguous()
        out = features.new_empty(self.shape[0], features.shape[1])
        args = (self.crow, self.col, self.steps, _step(features), features.numpy(), out.numpy())
        with threads():
            call_saying_compiled(gather_rows, "the frozen views' product kernel", *args)
        return out


def bytes_per_weight(n_columns: int) -> int:
    """A packed weight's bytes: its 16-bit step and its column index."""
    return 2 + (2 if n_columns <= SHORT_COLUMNS else 4)


def pack_blend(crow: Tensor, columns: Tensor, weights: Tensor, n_columns: int) -> PackedBlend:
    """The CSR matrix (crow [P + 1], columns [M], weights [M] in [0, 1], on the CPU) packed."""
    index = np.int32 if len(weights) < 2**31 else np.int64
    col = np.uint16 if n_columns <= SHORT_COLUMNS else np.int32
    steps = torch.round(weights.detach().float().clamp(0.0, 1.0) * WEIGHT_STEPS).to(torch.int32)
    shape = (len(crow) - 1, n_columns)
    return PackedBlend(crow.numpy().astype(index), columns.numpy().astype(col), steps.numpy().astype(np.uint16), shape)


def chunk_count(hits: int) -> int:
    return max(1, min(MAX_CHUNKS, hits // CHUNK_HITS))


@njit(cache=True, parallel=True)
def gather_rows(crow, col, steps, step, features, out):
    """out [P, C] = A features [N, C], A the packed matrix (crow [P + 1], col [M], steps [M]) [P, N]; `step` [1]:
    1 / WEIGHT_STEPS in the float type of the features."""
    p_count, c = out.shape
    real = features.dtype.type  # the 16-bit integers become floats of the features' type, not float64
    for p in prange(p_count):
        row = out[p]
        row[:] = 0
        for e in range(crow[p], crow[p + 1]):
            weight = real(steps[e]) * step[0]
            source = features[col[e]]
            for j in range(c):
                row[j] += weight * source[j]


@njit(cache=True, parallel=True)
def scatter_transposed(crow, col, steps, step, grad, chunks, out):
    """out [N, C] = A^T grad [P, C] (C-contiguous), A the packed matrix [P, N] as in `gather_rows`. Each chunk of
    rows (bounds by equal shares of the weights) adds into its own buffer; the buffers are summed in chunk order."""
    p_count, c = grad.shape
    n = out.shape[0]
    real = grad.dtype.type
    bounds = np.empty(chunks + 1, np.int64)
    bounds[0], bounds[chunks] = 0, p_count
    row = 0
    for k in range(1, chunks):
        while row < p_count and crow[row] < crow[p_count] * k // chunks:
            row += 1
        bounds[k] = row
    parts = np.empty((chunks, n * c), out.dtype)
    flat = grad.reshape(p_count * c)
    width = np.uint64(c)  # unsigned indices: no test for negative ones in the innermost loop
    for k in prange(chunks):
        part = parts[k]
        part[:] = 0
        for p in range(bounds[k], bounds[k + 1]):
            source = np.uint64(p) * width
            for e in range(crow[p], crow[p + 1]):
                target = np.uint64(col[e]) * width
                weight = real(steps[e]) * step[0]
                for j in range(width):
                    part[target + j] += weight * flat[source + j]
    for i in prange(n):
        for j in range(c):
            total = parts[0, i * c + j]
            for k in range(1, chunks):
                total += parts[k, i * c + j]
            out[i, j] = total


def transposed_product(matrix: PackedBlend, grad: Tensor) -> Tensor:  # [P, N], [P, C] -> [N, C]
    """matrix^T @ grad, in grad's float type."""
    grad = grad.contiguous()
    out = grad.new_empty(matrix.shape[1], grad.shape[1])  # new_empty: on grad's device (tests' stray-tensor check)
    args = (matrix.crow, matrix.col, matrix.steps, _step(grad), grad.numpy(), chunk_count(len(matrix.steps)))
    with threads():
        call_saying_compiled(scatter_transposed, "the frozen views' backward kernel", *args, out.numpy())
    return out


def _step(like: Tensor) -> np.ndarray:  # [1]: 1 / WEIGHT_STEPS in like's float type
    return np.array([1.0 / WEIGHT_STEPS], dtype=like.numpy().dtype)


def warm_up(np_dtype) -> None:
    """Compile (or load) the kernels for `np_dtype` features and matrices of 16-bit columns, as frozen views of up to
    2^16 Gaussians make them (backend numba's warm-up, which says itself what it compiled)."""
    matrix = PackedBlend(np.zeros(2, np.int32), np.zeros(0, np.uint16), np.zeros(0, np.uint16), (1, 1))
    step, ones = np.ones(1, np_dtype), np.zeros((1, 1), np_dtype)
    gather_rows(matrix.crow, matrix.col, matrix.steps, step, ones, np.empty((1, 1), np_dtype))
    scatter_transposed(matrix.crow, matrix.col, matrix.steps, step, ones, 1, np.empty((1, 1), np_dtype))
