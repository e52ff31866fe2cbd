"""Backend `numba` of `rasterize`: the torch backend's projection and blending rule in compiled loops on the CPU.

Two autograd Functions, each with a hand-written backward:

    _NumbaProjection:  means [N, 3], scales [N, 3], quats [N, 4]  ->  means2d [N, 2], conics [N, 3], depths [N]
    _NumbaRaster:      means2d, conics, opacities [N], features [N, C], depths  ->  image [H, W, C + 2]

(the image carries the features, the accumulated depth and alpha). means2d is the tensor between them, so
densification reads its gradient (`RasterOutput.screen`, retain_grad) as with backend torch. Only the exp of the
scales and the sigmoid of the opacities stay torch operations (their rounding is the reference's; see
numba_projection).

  - Projection (numba_projection.project, Gaussians in parallel): `project_gaussians` and `rasterize._setup` in
    the same float32 operations (the same bits: tests/test_numba_backend.py), the footprint boxes included; the
    drawn Gaussians sorted by depth (a radix sort of the float bits).
  - Binning: each drawn Gaussian goes to every 16 x 16 tile its footprint box meets, appended in depth order, so
    each tile's list is front to back.
  - Forward (numba_kernels.forward, tiles in parallel): per tile, its Gaussians in order, each over the pixel
    centres inside its footprint ellipse (the same float32 arithmetic as the torch backend's candidate pairs),
    alpha = min(max_alpha, o exp(-d^T conic d / 2)) skipped below min_alpha, the transmittance as a float64
    product, the early stop before it would fall below min_transmittance. When backward will run, each blended
    hit is written down (its pixel and response), so backward neither finds the pixels again nor recomputes exp.
  - Backward (numba_kernels.backward_recorded, or `backward` when the record would be too large): per tile, its
    Gaussians back to front, the transmittance in front of each hit recovered from the one behind it, with
    S = sum of alpha_j T_j q_j over the hits behind (q = <dL/dout, value>), as blend.py's backward. One gradient
    row per (tile, Gaussian) entry, then a per-Gaussian sum in entry order: the same bits whatever the thread
    count, run after run. Then the projection's backward, per Gaussian.

The kernels are compiled at the first use in a process, or loaded from numba's cache (`cache=True`: __pycache__
beside this module, or $NUMBA_CACHE_DIR); a compilation (a cache miss) is said once per process on stderr with
its time. Threads: as many as torch uses ($MATSPRAY_THREADS through matspray.device.configure_threads).
"""

from __future__ import annotations

import os
import sys
import threading
import time

import numpy as np
import torch
from torch import Tensor

from matspray.render.numba.threads import threads
from matspray.render.projection import max_eigen_radius
from matspray.render.settings import RasterSettings

_READY: set = set()  # dtypes whose kernels this process has compiled or loaded (added once the warm-up is done)
_WARMING: dict = {}  # dtype -> the thread compile_in_background started for it
_WARMING_LOCK = threading.Lock()
_COMPILE_LOCK = threading.RLock()  # held through a warm-up: other threads wait; the warm-up's own calls come back in
_COMPILING: set = set()  # dtypes whose warm-up the holder of _COMPILE_LOCK is running
_TOLD = False  # whether a compilation was already reported


def kernels():
    """The kernel module (imported on first use: importing numba takes a moment, and only this backend needs it)."""
    from matspray.render.numba import kernels as numba_kernels

    return numba_kernels


def rasterize_gaussians(
    gaussians,  # matspray.gaussians.Gaussians
    camera,  # matspray.data.camera.Camera
    features: Tensor,  # [N, C]
    settings: RasterSettings,
    absgrad: bool = False,  # backward also gives means2d.absgrad [N, 2], as blend.blend_hits does
) -> tuple[
    Tensor, int, Tensor, Tensor
]:  # image [H, W, C + 2] (features, depth, alpha), hits, means2d [N, 2], radii [N]
    """Project and blend: two autograd Functions, the projection's output means2d between them, so that
    `RasterOutput.screen` is a tensor of the graph whose gradient densification reads (retain_grad)."""
    if gaussians.means.device.type != "cpu":
        raise ValueError(f"rasterize: backend numba renders on the CPU, the Gaussians are on {gaussians.means.device}")
    dtype = features.dtype
    np_dtype = np.float64 if dtype == torch.float64 else np.float32
    ensure_compiled(np_dtype)
    layout = _Layout(camera, settings, np_dtype)
    # only a render that backward will run through records its hits
    layout.record = torch.is_grad_enabled() and any(
        t.requires_grad
        for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, features)
    )
    # torch's exp and sigmoid (the reference's own rounding; see numba_projection), everything else compiled
    opacities = gaussians.opacities.to(dtype)
    means2d, conics, depths = _NumbaProjection.apply(
        gaussians.means.to(dtype), gaussians.scales.to(dtype), gaussians.quats.to(dtype), opacities, layout
    )
    image, hits = _NumbaRaster.apply(
        means2d, conics, opacities, features, depths, (layout, means2d if absgrad else None)
    )
    return image, int(hits), means2d, layout.radii


class _Layout:
    """What the two Functions share beyond the differentiable inputs: the camera and settings as arrays of the
    float type, the footprints (projection forward) and the tile lists."""

    def __init__(self, camera, settings: RasterSettings, np_dtype):
        self.np_dtype = np_dtype
        self.height, self.width = height, width = camera.height, camera.width
        self.view, self.consts = _camera_arrays(camera, settings, np_dtype)
        self.tiles_x, self.tiles_y = -(-width // 16), -(-height // 16)
        self.grid = _grid(max(height, width) + 1, np_dtype)
        self.blend_consts = np.array([0.5, settings.min_alpha, settings.max_alpha, 0.0], dtype=np_dtype)
        self.min_transmittance = float(settings.min_transmittance)

    def footprints(self, boxes, det, a_r2, depths, cov2d, flags) -> None:
        """From the projection's forward: the pixel boxes and footprint terms, the radii (`_setup`'s, in torch:
        see numba_projection) and the tile lists in depth order."""
        self.boxes, self.det, self.a_r2 = boxes, det, a_r2
        radii = max_eigen_radius(torch.from_numpy(cov2d))
        self.radii = radii.masked_fill_(torch.from_numpy(flags & 4) == 0, 0.0)
        with threads() as pool:
            order = projection().depth_order(depths, boxes)
            (
                self.offsets,
                self.ids,
                self.g_offsets,
                self.slot,
                self.record_offsets,
                self.tile_order,
                self.worker_offsets,
            ) = kernels().bin_tiles(boxes, order, self.tiles_x, self.tiles_y, pool.count)

    def common(self, means2d, conics, opacities, values) -> tuple:
        return (
            means2d,
            conics,
            opacities,
            values,
            self.det,
            self.a_r2,
            self.boxes,
            self.offsets,
            self.ids,
            self.tile_order,
            self.worker_offsets,
            self.height,
            self.width,
            self.tiles_x,
            self.grid,
            self.blend_consts,
        )


RECORD_BUDGET = 1 << 25  # recorded hits at most (about 170 MB in float32)
_GRIDS: dict = {}
_CAMERAS: dict = {}


def _grid(size: int, np_dtype) -> np.ndarray:  # grid[i] = i in the float type (see numba_kernels)
    key = (size, np.dtype(np_dtype).name)
    if key not in _GRIDS:
        _GRIDS[key] = np.arange(size, dtype=np_dtype)
    return _GRIDS[key]


def _camera_arrays(camera, settings: RasterSettings, np_dtype) -> tuple[np.ndarray, np.ndarray]:
    """viewmat's [3, 4] and numba_projection's constants, as float32 (or float64) arrays computed by the same
    torch expressions as project_gaussians (the clamp limits round as there). Kept for the last few cameras:
    training renders each view many times."""
    key = (id(camera.viewmat), id(camera.K), camera.width, camera.height, settings, np.dtype(np_dtype).name)
    hit = _CAMERAS.get(key)
    if (
        hit is not None
        and hit[0] is camera.viewmat
        and hit[1] is camera.K
        and hit[2] == (camera.viewmat._version, camera.K._version)
    ):
        return hit[3], hit[4]
    from matspray.render.numba import projection as P
    from matspray.render.projection import JACOBIAN_FOV_MARGIN

    dtype = torch.float64 if np_dtype == np.float64 else torch.float32
    K = camera.K.to(dtype)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    width, height = camera.width, camera.height
    consts = np.zeros(P.NUM_CONSTS, np_dtype)
    limits = (
        JACOBIAN_FOV_MARGIN * cx / fx,
        JACOBIAN_FOV_MARGIN * (width - cx) / fx,
        JACOBIAN_FOV_MARGIN * cy / fy,
        JACOBIAN_FOV_MARGIN * (height - cy) / fy,
    )
    for index, value in zip(
        (P.LIM_X_LO, P.LIM_X_HI, P.LIM_Y_LO, P.LIM_Y_HI, P.FX, P.FY, P.CX, P.CY), (*limits, fx, fy, cx, cy)
    ):
        consts[index] = value.item()
    for index, value in (
        (P.NEAR, settings.near),
        (P.EPS2D, settings.eps2d),
        (P.DET_REL, 1e-12),
        (P.DET_FLOOR, 1e-30),
        (P.MIN_ALPHA, settings.min_alpha),
        (P.MARGIN, 1e-3),
        (P.HALF, 0.5),
        (P.THREE, 3.0),
        (P.ONE, 1.0),
        (P.TWO, 2.0),
        (P.ZERO, 0.0),
        (P.WIDTH, width),
        (P.HEIGHT, height),
        (P.NORM_EPS, 1e-12),
        (P.CONIC_FLOOR, 1e-30),
    ):
        consts[index] = value
    view = np.ascontiguousarray(camera.viewmat[:3, :4].to(dtype).cpu().numpy())
    if len(_CAMERAS) > 256:
        _CAMERAS.clear()
    _CAMERAS[key] = (camera.viewmat, camera.K, (camera.viewmat._version, camera.K._version), view, consts)
    return view, consts


class _NumbaProjection(torch.autograd.Function):
    """(means, scales, quats) -> (means2d, conics, depths); opacities only decide which Gaussians are drawn."""

    @staticmethod
    def forward(ctx, means, scales, quats, opacities, layout):
        arrays = [_numpy(t, layout.np_dtype) for t in (means, scales, quats, opacities)]
        with threads():
            means2d, conics, depths, cov2d, boxes, det, a_r2, flags = projection().project(
                *arrays, layout.view, layout.consts
            )
        layout.footprints(boxes, det, a_r2, depths, cov2d, flags)
        layout.opacities = arrays[3]
        ctx.layout, ctx.arrays, ctx.flags = layout, arrays[:3], flags
        return torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths)

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths):
        layout = ctx.layout
        grads = [
            np.zeros(shape, layout.np_dtype) if grad is None else _numpy(grad, layout.np_dtype)
            for grad, shape in (
                (grad_means2d, (len(ctx.flags), 2)),
                (grad_conics, (len(ctx.flags), 3)),
                (grad_depths, len(ctx.flags)),
            )
        ]
        with threads():
            grad_means, grad_scales, grad_quats = projection().project_backward(
                *ctx.arrays, layout.view, layout.consts, ctx.flags, *grads
            )
        return torch.from_numpy(grad_means), torch.from_numpy(grad_scales), torch.from_numpy(grad_quats), None, None


class _NumbaRaster(torch.autograd.Function):
    """(means2d, conics, opacities, features, depths) -> image [H, W, C + 2]: the features, the depths and 1 blended."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, depths, extra):
        layout, absgrad_of = extra
        values = np.empty((features.shape[0], features.shape[1] + 2), layout.np_dtype)
        values[:, :-2] = features.detach().numpy()
        values[:, -2] = depths.detach().numpy()
        values[:, -1] = 1.0
        arrays = [_numpy(t, layout.np_dtype) for t in (means2d, conics)] + [layout.opacities, values]
        room = int(layout.record_offsets[-1])
        # the blended hits written down for backward (pixel, response: 5 bytes in float32), unless that would take
        # more than RECORD_BUDGET entries: then backward finds and recomputes them
        record = (
            (np.empty(room, np.uint8), np.empty(room, layout.np_dtype), np.empty(len(layout.ids), np.int64))
            if layout.record and room <= RECORD_BUDGET
            else (np.empty(0, np.uint8), np.empty(0, layout.np_dtype), np.empty(0, np.int64))
        )
        with threads():
            image, final_t, last, tile_hits = kernels().forward(
                *layout.common(*arrays), layout.min_transmittance, layout.record_offsets, *record
            )
        ctx.layout, ctx.absgrad_of, ctx.arrays, ctx.state, ctx.record = (
            layout,
            absgrad_of,
            arrays,
            (final_t, last),
            record,
        )
        ctx.tile_hits = tile_hits
        ctx.dtype = features.dtype
        return torch.from_numpy(image), int(tile_hits.sum())

    @staticmethod
    def backward(ctx, grad_image, _grad_hits):
        layout = ctx.layout
        grad = _numpy(grad_image, layout.np_dtype)
        with threads() as pool:
            if len(ctx.record[0]):
                means2d, conics, opacities, values = ctx.arrays
                # the tiles split among the threads by the hits each blended (the forward's split is by box pixels)
                tile_order, worker_offsets = kernels().partition(ctx.tile_hits, pool.count)
                entry_grads = kernels().backward_recorded(
                    means2d,
                    conics,
                    opacities,
                    values,
                    layout.offsets,
                    layout.ids,
                    tile_order,
                    worker_offsets,
                    layout.width,
                    layout.height,
                    layout.tiles_x,
                    layout.grid,
                    layout.blend_consts,
                    layout.slot,
                    ctx.state[0],
                    layout.record_offsets,
                    *ctx.record,
                    grad,
                )
            else:
                entry_grads = _unrecorded_backward(layout.common(*ctx.arrays), layout.slot, ctx.state, grad)
            per_gaussian = kernels().reduce_entries(entry_grads, layout.g_offsets)
        sums = torch.from_numpy(per_gaussian).to(ctx.dtype)  # [N, 8 + C + 2]
        if ctx.absgrad_of is not None:
            target = ctx.absgrad_of
            if (
                getattr(target, "absgrad", None) is None
            ):  # as blend.add_absgrad: created once, added to by each backward
                target.absgrad = torch.zeros_like(target, memory_format=torch.contiguous_format).detach()
            target.absgrad += sums[:, 6:8].to(target.dtype)
        return sums[:, 0:2], sums[:, 2:5], sums[:, 5], sums[:, 8:-2], sums[:, -2], None


def numba_view_blend(gaussians, camera, settings: RasterSettings = RasterSettings()):
    """A view's blend matrix [H W, N] on backend numba, in CSR order (`weights.recorded_blend`): row pointers
    crow [H W + 1] int64, Gaussian ids [M] int64 and weights [M] float32, by pixel (row-major) then Gaussian; each
    Gaussian's coverage [N] (its weights' sum) and the Gaussians with a weight [K] (increasing). None when the
    forward's record would pass RECORD_BUDGET (the torch version does those)."""
    from matspray.render.backend import note_render
    from matspray.render.numba.weights import recorded_blend

    note_render("numba")
    ensure_compiled(np.float32)  # (its warm-up compiles `recorded_blend` too)
    layout = _Layout(camera, settings, np.float32)
    with torch.no_grad():  # the projection as a render makes it (footprints and tile lists into `layout`)
        g = gaussians.detach()
        means2d, conics, _ = _NumbaProjection.apply(g.means, g.scales, g.quats, g.opacities, layout)
    means2d, conics, opacities = _numpy(means2d, np.float32), _numpy(conics, np.float32), layout.opacities
    room = int(layout.record_offsets[-1])
    if room > RECORD_BUDGET:
        return None
    record = (np.empty(room, np.uint8), np.empty(room, np.float32), np.empty(len(layout.ids), np.int64))
    values = np.ones((len(opacities), 1), np.float32)  # alpha's channel only
    with threads():
        kernels().forward(
            *layout.common(means2d, conics, opacities, values), layout.min_transmittance, layout.record_offsets, *record
        )
        found = recorded_blend(
            layout.ids,
            layout.offsets,
            opacities,
            layout.record_offsets,
            *record,
            layout.tiles_x,
            layout.width,
            layout.height,
            layout.blend_consts,
        )
    crow, columns, weights, coverage, hits = (torch.from_numpy(array) for array in found)
    return crow, columns, weights, coverage, torch.nonzero(hits).squeeze(1)


def _unrecorded_backward(common: tuple, slot, state: tuple, grad):
    """numba_kernels.backward, for renders whose record would pass RECORD_BUDGET (large images with many Gaussians).
    It is not part of `ensure_compiled`'s warm-up (most runs never need it): compiled at its first use instead, which
    is said once on stderr with its time, and cached as the others."""
    what = f"the backward kernel for renders of more than {RECORD_BUDGET} hits"
    return kernels().call_saying_compiled(kernels().backward, what, *common, slot, *state, grad)


def _dispatchers(*modules) -> list:
    """Every compiled function of the kernel modules (those inlined into others never compile on their own, and a
    kernel not warmed up, such as the unrecorded backward, compiles later: neither moves the count of misses)."""
    from numba.core.dispatcher import Dispatcher

    return [f for m in modules for f in vars(m).values() if isinstance(f, Dispatcher) and f.__module__ == m.__name__]


def projection():
    """The projection kernels' module (imported on first use, as `kernels`)."""
    from matspray.render.numba import projection as numba_projection

    return numba_projection


def _numpy(tensor: Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=dtype)


def ensure_compiled(np_dtype) -> None:
    """Run every kernel of backend numba once on tiny inputs (the rasterizer's on one Gaussian in a 16 x 16 image,
    SH colour, normals, lifting's rays), so that compiling (or loading from the cache) happens here, all at once; the
    first compilation in a process is said on stderr with its time. While `compile_in_background` is at it, waits
    for it."""
    key = np.dtype(np_dtype).name
    warming = _WARMING.get(key)
    if warming is not None and warming is not threading.current_thread():
        warming.join()
        return
    if key in _READY:
        return
    with _COMPILE_LOCK:  # another thread's ensure_compiled waits here until the kernels are ready
        if key in _READY or key in _COMPILING:  # ready meanwhile, or the warm-up's own call (it builds a _Layout)
            return
        _COMPILING.add(key)
        try:
            _compile(key, np_dtype)
        finally:
            _COMPILING.discard(key)
        _READY.add(key)  # only once every kernel has run: a failed warm-up leaves the dtype not ready


def _compile(key: str, np_dtype) -> None:
    """ensure_compiled's warm-up, timed, and said on stderr where it compiled (the first time in the process)."""
    global _TOLD
    from matspray.render.numba import normals as numba_normals
    from matspray.render.numba import rays as numba_rays
    from matspray.render.numba import sh as numba_sh
    from matspray.render.numba import sparse as numba_sparse
    from matspray.render.numba import weights as numba_weights

    module = kernels()
    dispatchers = _dispatchers(module, projection(), numba_sh, numba_normals, numba_rays, numba_weights, numba_sparse)
    misses = module.cache_misses(dispatchers)
    start = time.perf_counter()
    # numba's OpenMP layer loads its own libgomp at the first parallel loop, and libgomp reads OMP_WAIT_POLICY
    # then: passive, its idle threads sleep rather than spin after each kernel while torch's threads need the
    # cores (spinning threads take the cores from those with work: docs/defaults.md).
    # Torch's own libgomp read the variable when torch was imported and keeps its policy; set by the user, it stays.
    told = os.environ.get("OMP_WAIT_POLICY")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        _warm_up(np_dtype)
    finally:
        if told is None:
            os.environ.pop("OMP_WAIT_POLICY", None)
    compiled = module.cache_misses(dispatchers) > misses
    if compiled and not _TOLD:
        _TOLD = True
        where = module.bin_tiles.stats.cache_path
        print(
            f"numba: compiled the CPU kernels ({key}: rasterizer, SH colour, normals, lifting's rays, frozen views) in "
            f"{time.perf_counter() - start:.1f} s, once: later runs load them from {where}",
            file=sys.stderr,
            flush=True,
        )


def compile_in_background(np_dtype=np.float32) -> None:
    """Start `ensure_compiled` in a daemon thread, so that a run compiles (a fresh install) or loads the kernels
    while it reads or makes its data; the first render waits for the rest. Once per process and dtype."""
    key = np.dtype(np_dtype).name
    with _WARMING_LOCK:
        if key in _READY or key in _WARMING:
            return
        thread = threading.Thread(target=ensure_compiled, args=(np_dtype,), daemon=True, name="matspray-numba")
        _WARMING[key] = thread
    thread.start()


@torch.enable_grad()  # the first render may come under no_grad; the backward kernels are warmed up too
def _warm_up(np_dtype) -> None:
    from matspray.data.camera import Camera
    from matspray.gaussians import Gaussians

    dtype = torch.float64 if np_dtype == np.float64 else torch.float32
    camera = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 0.7, 16, 16)
    gaussians = Gaussians(
        torch.zeros(1, 3, dtype=dtype, requires_grad=True),
        torch.full((1, 3), -1.0, dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
        torch.zeros(1, dtype=dtype),
        torch.zeros(1, 1, 3, dtype=dtype),
    )
    image, _, _, _ = rasterize_gaussians(gaussians, camera, torch.ones(1, 1, dtype=dtype), RasterSettings())
    image.sum().backward()  # the recorded backward (the unrecorded one compiles when first needed)
    from matspray.render.numba.normals import CompiledNormals
    from matspray.render.numba.rays import trace_view
    from matspray.render.numba.sh import CompiledSH

    sh = torch.zeros(1, 16, 3, dtype=dtype, requires_grad=True)
    CompiledSH.apply(sh, gaussians.means, camera.center, 3).sum().backward()
    quats = gaussians.quats.detach().requires_grad_(True)
    CompiledNormals.apply(quats, gaussians.log_scales, gaussians.means, camera.center).sum().backward()
    on_object = torch.ones(camera.height * camera.width, dtype=torch.bool)
    trace_view(gaussians.detach(), camera, on_object, 2, torch.zeros(1), 1.0, RasterSettings(), 0.0)
    from matspray.render.numba.sparse import warm_up

    warm_up(np_dtype)  # frozen views' backward pass
    if np_dtype == np.float32:  # frozen views' weights (float32 only)
        from matspray.render.numba.weights import recorded_blend

        empty = np.zeros(0, np.int64)
        recorded_blend(
            empty,
            np.zeros(2, np.int64),
            np.zeros(1, np.float32),
            np.zeros(2, np.int64),
            np.zeros(0, np.uint8),
            np.zeros(0, np.float32),
            empty,
            1,
            16,
            16,
            np.zeros(4, np.float32),
        )
