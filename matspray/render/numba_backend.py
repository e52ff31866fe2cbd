"""Backend `numba` of `rasterize`: the torch backend's blending rule in compiled tile loops on the CPU.

The projection (means2d, conics, depths) stays in torch autograd (matspray.render.projection), so gradients
reach means, log_scales and quats through torch; this module is one autograd Function from the projected
splats to the image:

    means2d [N, 2], conics [N, 3], opacities [N], values [N, K]  ->  image [H, W, K]

with a hand-written backward that returns the gradients of all four (and, on request, gsplat's absgrad).

  - Binning: each drawable Gaussian goes to every 16 x 16 tile its footprint box (the torch backend's pixel box)
    meets, appended in the torch backend's depth order, so each tile's list is front to back with the same ties.
  - Forward (numba_kernels.forward, tiles in parallel): per tile, its Gaussians in order, each over the pixel
    centres inside its footprint ellipse (the same float32 arithmetic as the torch backend's candidate pairs),
    alpha = min(max_alpha, o exp(-d^T conic d / 2)) skipped below min_alpha, the transmittance as a float64 sum of
    log(1 - alpha), and the early stop before it would fall below min_transmittance. Kept per pixel: the final
    log transmittance and the entry index of the last blended hit.
  - Backward (numba_kernels.backward): per tile, its Gaussians back to front, recomputing each hit and the
    transmittance in front of it (final log T minus the terms behind), with S = sum of alpha_j T_j q_j over the
    hits behind (q = <dL/dout, value>), as blend.py's backward. One gradient row per (tile, Gaussian) entry,
    then a per-Gaussian sum in entry order: the same bits whatever the thread count, run after run.

The kernels are compiled at the first use in a process, or loaded from numba's cache (`cache=True`: __pycache__
beside this module, or $NUMBA_CACHE_DIR); a compilation (a cache miss) is said once per process on stderr with
its time. Threads: as many as torch uses ($MATSPRAY_THREADS through matspray.device.configure_threads).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import torch
from torch import Tensor

from matspray.render.settings import RasterSettings

_READY: set = set()  # dtypes whose kernels this process has compiled or loaded
_TOLD = False  # whether a compilation was already reported


def kernels():
    """The kernel module (imported on first use: importing numba takes a moment, and only this backend needs it)."""
    from matspray.render import numba_kernels

    return numba_kernels


def rasterize_splats(
    means2d: Tensor,  # [N, 2] projected centres (in the autograd graph)
    conics: Tensor,  # [N, 3] (a, b, c) of the inverse 2D covariance
    opacities: Tensor,  # [N]
    values: Tensor,  # [N, K] what to blend
    footprints: tuple[Tensor, Tensor, Tensor],  # boxes [N, 4] long, radius2 [N], ranks [N] (rasterize._setup's, no grad)
    height: int,
    width: int,
    settings: RasterSettings,
    absgrad_of: Tensor | None = None,  # receives .absgrad [N, 2] in backward, as blend.blend_hits does
) -> tuple[Tensor, int]:  # image [H, W, K], number of blended (Gaussian, pixel) hits
    if means2d.device.type != "cpu":
        raise ValueError(f"rasterize: backend numba renders on the CPU, the Gaussians are on {means2d.device}")
    dtype = values.dtype
    means2d, conics, opacities = means2d.to(dtype), conics.to(dtype), opacities.to(dtype)
    layout = _Layout(conics.detach(), footprints, height, width, settings, dtype)
    image, hits = _NumbaRaster.apply(means2d, conics, opacities, values, (layout, absgrad_of))
    return image, int(hits)


class _Layout:
    """What forward and backward share beyond the differentiable inputs: the footprints as numpy arrays,
    the tile lists and the constants."""

    def __init__(self, conics: Tensor, footprints, height: int, width: int, settings: RasterSettings, dtype):
        boxes, radius2, ranks = footprints
        with torch.no_grad():
            a, b, c = conics.unbind(-1)
            # the torch backend's candidate pairs compute these from float32 footprints: done here the same way
            det = (a * c - b * b).clamp_min(1e-30)
            a_r2 = a * radius2.to(dtype)
            order = torch.empty_like(ranks)  # the depth order itself: the inverse of the ranks, no second sort
            order[ranks] = torch.arange(len(ranks), device=ranks.device)
        self.np_dtype = np.float64 if dtype == torch.float64 else np.float32
        self.det, self.a_r2 = _numpy(det, self.np_dtype), _numpy(a_r2, self.np_dtype)
        self.boxes = _numpy(boxes, np.int64)
        self.height, self.width = height, width
        self.tiles_x = -(-width // 16)
        self.tiles_y = -(-height // 16)
        # numba splits a parallel loop into one contiguous block per thread: the tiles are visited in a fixed shuffled
        # order, so that each block mixes the object's busy middle with the empty border (numba's dynamic
        # scheduling, set_parallel_chunksize, measured 2-4x slower kernels here)
        self.tile_order = np.random.default_rng(0).permutation(self.tiles_x * self.tiles_y).astype(np.int64)
        self.grid = np.arange(max(height, width) + 1, dtype=self.np_dtype)
        self.consts = np.array([0.5, settings.min_alpha, settings.max_alpha, 0.0], dtype=self.np_dtype)
        self.min_transmittance = float(settings.min_transmittance)
        ensure_compiled(self.np_dtype)
        with threads():
            self.offsets, self.ids, self.g_offsets, self.by_gaussian = kernels().bin_tiles(
                self.boxes, _numpy(order, np.int64), self.tiles_x, self.tiles_y)

    def common(self, means2d, conics, opacities, values) -> tuple:
        return (means2d, conics, opacities, values, self.det, self.a_r2, self.boxes, self.offsets, self.ids,
                self.tile_order, self.height, self.width, self.tiles_x, self.grid, self.consts)


class _NumbaRaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, values, extra):
        layout, absgrad_of = extra
        arrays = [_numpy(t.detach(), layout.np_dtype) for t in (means2d, conics, opacities, values)]
        with threads():
            image, final_t, last, tile_hits = kernels().forward(*layout.common(*arrays), layout.min_transmittance)
        ctx.layout, ctx.absgrad_of, ctx.arrays, ctx.state = layout, absgrad_of, arrays, (final_t, last)
        ctx.dtype = values.dtype
        hits = torch.tensor(int(tile_hits.sum()))
        ctx.mark_non_differentiable(hits)
        return torch.from_numpy(image), hits

    @staticmethod
    def backward(ctx, grad_image, _grad_hits):
        layout = ctx.layout
        grad = np.ascontiguousarray(grad_image.detach().to(ctx.dtype).numpy())
        with threads():
            entry_grads = kernels().backward(*layout.common(*ctx.arrays), *ctx.state, grad)
        with threads():
            per_gaussian = kernels().reduce_entries(entry_grads, layout.g_offsets, layout.by_gaussian)
        sums = torch.from_numpy(per_gaussian).to(ctx.dtype)  # [N, 8 + K]
        if ctx.absgrad_of is not None:
            target = ctx.absgrad_of
            if getattr(target, "absgrad", None) is None:  # as blend.add_absgrad: created once, added to by each backward
                target.absgrad = torch.zeros_like(target, memory_format=torch.contiguous_format).detach()
            target.absgrad += sums[:, 6:8].to(target.dtype)
        return sums[:, 0:2], sums[:, 2:5], sums[:, 5], sums[:, 8:], None


def _numpy(tensor: Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=dtype)


class threads:
    """Numba's threads for the block: as many as torch's (what $MATSPRAY_THREADS sets), at most numba's pool."""

    def __enter__(self):
        import numba

        self.before = numba.get_num_threads()
        numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
        return self

    def __exit__(self, *exc):
        import numba

        numba.set_num_threads(self.before)


def ensure_compiled(np_dtype) -> None:
    """Run every kernel once on one Gaussian in a 16 x 16 image, so that compiling (or loading from the cache)
    happens here, all at once; the first compilation in a process is said on stderr with its time."""
    global _TOLD
    key = np.dtype(np_dtype).name
    if key in _READY:
        return
    module = kernels()
    dispatchers = (module.bin_tiles, module.forward, module.backward, module.reduce_entries)
    misses = sum(sum(d.stats.cache_misses.values()) for d in dispatchers)
    start = time.perf_counter()
    _READY.add(key)  # before the call below, which builds a _Layout and comes back here
    # numba's OpenMP layer loads its own libgomp at the first parallel loop, and libgomp reads OMP_WAIT_POLICY
    # then: passive, its idle threads sleep rather than spin after each kernel while torch's threads need the
    # cores (measured on a shared 2-core machine: spinning made fwd+bwd with 2 threads 20-30x slower).
    # Torch's own libgomp read the variable when torch was imported and keeps its policy; set by the user, it stays.
    told = os.environ.get("OMP_WAIT_POLICY")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        _warm_up(np_dtype)
    finally:
        if told is None:
            os.environ.pop("OMP_WAIT_POLICY", None)
    compiled = sum(sum(d.stats.cache_misses.values()) for d in dispatchers) > misses
    if compiled and not _TOLD:
        _TOLD = True
        where = module.bin_tiles.stats.cache_path
        print(f"numba: compiled the rasterizer's kernels ({key}) in {time.perf_counter() - start:.1f} s, once: "
              f"later runs load them from {where}", file=sys.stderr, flush=True)


@torch.enable_grad()  # the first render may come under no_grad; the backward kernels are warmed up too
def _warm_up(np_dtype) -> None:
    dtype = torch.float64 if np_dtype == np.float64 else torch.float32
    means2d = torch.tensor([[8.0, 8.0]], dtype=dtype, requires_grad=True)
    conics = torch.tensor([[0.25, 0.0, 0.25]], dtype=dtype)
    opacities = torch.tensor([0.5], dtype=dtype)
    values = torch.ones(1, 1, dtype=dtype)
    boxes = torch.tensor([[0, 0, 15, 15]])
    image, _ = rasterize_splats(means2d, conics, opacities, values, (boxes, torch.tensor([20.0]), torch.zeros(1, dtype=torch.long)),
                                16, 16, RasterSettings())
    image.sum().backward()
