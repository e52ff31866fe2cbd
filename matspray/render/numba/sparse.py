"""The backward pass of frozen views' blend on the CPU (matspray.render.raster.gbuffer.SparseBlend): the product of the
transpose of a view's CSR blend matrix [pixels, Gaussians] with the image's gradient, without keeping that transpose
(half the frozen views' memory: docs/dev/real-captures.md, "Frozen views without their transposes").

Rows are cut into chunks of about CHUNK_HITS weights; each chunk scatters its rows into a [N, C] buffer of its own
(chunks run in parallel), and the buffers are summed in chunk order. The chunks depend on the matrix only, so the
gradient has the same bits whatever the thread count.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from numba import prange
from torch import Tensor

from matspray.render.numba.kernels import njit
from matspray.render.numba.threads import threads

CHUNK_HITS = 1 << 18  # weights per chunk: a chunk's [N, C] buffer costs about as much as scattering them
MAX_CHUNKS = 16  # at most this many [N, C] buffers at once
_TOLD = False  # whether a compilation of the kernel was said on stderr


def chunk_count(hits: int) -> int:
    return max(1, min(MAX_CHUNKS, hits // CHUNK_HITS))


@njit(cache=True, parallel=True)
def scatter_transposed(crow, col, val, grad, chunks, out):
    """out [N, C] = A^T grad, A the CSR matrix (crow [P + 1], col [M], val [M]) [P, N], grad [P, C] C-contiguous.
    Each chunk of rows (bounds by equal shares of the weights) adds into its own buffer; the buffers are summed in
    chunk order."""
    p_count, c = grad.shape
    n = out.shape[0]
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
                weight = val[e]
                for j in range(width):
                    part[target + j] += weight * flat[source + j]
    for i in prange(n):
        for j in range(c):
            total = parts[0, i * c + j]
            for k in range(1, chunks):
                total += parts[k, i * c + j]
            out[i, j] = total


def transposed_product(matrix: Tensor, grad: Tensor) -> Tensor:  # CSR [P, N] on the CPU, [P, C] -> [N, C]
    """matrix^T @ grad, in matrix's float type (grad's must be the same), on numba's threads (as many as torch's)."""
    grad = grad.contiguous()
    out = grad.new_empty(matrix.shape[1], grad.shape[1])  # new_empty: on grad's device (tests' stray-tensor check)
    values = matrix.values()
    args = (matrix.crow_indices().numpy(), matrix.col_indices().numpy(), values.numpy(), grad.numpy())
    misses = None if _TOLD else _misses()  # counted until a compilation was said: not on every backward pass
    start = time.perf_counter()
    with threads():
        scatter_transposed(*args, chunk_count(len(values)), out.numpy())
    if misses is not None:
        _tell_compiled(misses, start)
    return out


def _misses() -> int:
    return sum(scatter_transposed.stats.cache_misses.values())


def _tell_compiled(misses: int, start: float) -> None:
    """Say once per process on stderr that the kernel was compiled (backend numba's warm-up compiles it; backend
    torch on the CPU compiles it at its first backward pass), and where later runs load it from."""
    global _TOLD
    if _misses() == misses:
        return
    _TOLD = True
    print(
        f"numba: compiled the frozen views' backward kernel in {time.perf_counter() - start:.1f} s, once: later runs "
        f"load it from {scatter_transposed.stats.cache_path}",
        file=sys.stderr,
        flush=True,
    )


def warm_up(np_dtype) -> None:
    """Compile (or load) the kernel for `np_dtype` weights with 32-bit indices, as frozen views make them (backend
    numba's warm-up, which says itself what it compiled)."""
    empty = np.zeros(0, np.int32)
    scatter_transposed(
        np.zeros(2, np.int32), empty, np.zeros(0, np_dtype), np.zeros((1, 1), np_dtype), 1, np.empty((1, 1), np_dtype)
    )
