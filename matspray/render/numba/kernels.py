"""The compiled loops of backend `numba` (matspray.render.numba.backend): tile binning, forward blending, the
reverse pass and the per-Gaussian reduction of its gradients.

Every kernel is generic in the float type of its inputs (float32 for rendering, float64 for gradcheck): constants
come in `consts`, an array of that type, and integers become floats through `grid` (grid[i] = i), because numba
promotes float32 arithmetic with a Python float or an integer to float64, and the hit test must round exactly as
the torch backend's float32 arithmetic does (see `_row_span`).

consts: [0] 0.5, [1] min_alpha, [2] max_alpha, [3] 0 (RasterSettings' values in the float type of the inputs).
"""

from __future__ import annotations

import sys
import time

import numpy as np
from numba import njit as _njit
from numba import prange


def njit(**options):
    """numba.njit with its on-disk cache (__pycache__ beside this file, or $NUMBA_CACHE_DIR), so that only the
    first run compiles; where numba finds no writable place for it (it raises at decoration), compile per process."""

    def wrap(function):
        try:
            return _njit(**options)(function)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            return _njit(**{k: v for k, v in options.items() if k != "cache"})(function)

    return wrap


_CALLED: set = set()  # (kernel, its arguments' types) run before in this process: they cannot compile again


def cache_misses(dispatchers) -> int:
    """How many compilations numba's on-disk cache could not spare these kernels so far in this process."""
    return sum(sum(d.stats.cache_misses.values()) for d in dispatchers)


def call_saying_compiled(kernel, what: str, *args):
    """kernel(*args); at the first call for its arguments' types, one line on stderr if numba compiled it then
    (`what` names it), with the time and where later runs load it from. Later calls only run it."""
    key = (kernel, tuple((a.dtype, a.ndim) if isinstance(a, np.ndarray) else type(a) for a in args))
    if key in _CALLED:
        return kernel(*args)
    misses, start = cache_misses([kernel]), time.perf_counter()
    result = kernel(*args)
    _CALLED.add(key)
    if cache_misses([kernel]) > misses:
        print(
            f"numba: compiled {what} in {time.perf_counter() - start:.1f} s, once: later runs load it from "
            f"{kernel.stats.cache_path}",
            file=sys.stderr,
            flush=True,
        )
    return result


TILE = 16  # pixels per tile side
# gradients kept per (tile, Gaussian) entry besides the values': mean x, y; conic a, b, c; opacity; |mean x|, |mean y|
PER_ENTRY = 8


@njit(cache=True)
def bin_tiles(boxes, order, tiles_x, tiles_y, num_workers):
    """Tile lists: entry e of tile t (offsets[t] <= e < offsets[t + 1]) is Gaussian ids[e]; each tile's Gaussians
    are front to back because they are appended in `order` (the torch backend's depth order). slot[e]: the row of
    entry e in the backward's entry gradients, which groups each Gaussian's entries (g_offsets[g] <= slot <
    g_offsets[g + 1]) in increasing entry order, so the per-Gaussian reduction reads them in a fixed order and
    contiguously; record_offsets [T + 1], each tile's room for the forward's record of its hits (every pixel of
    every entry's box in the tile: a bound on its hits). Also the forward's tiles split among `num_workers`
    threads by that room (`partition`). One pass to count, one to place."""
    n = boxes.shape[0]
    num_tiles = tiles_x * tiles_y
    offsets = np.zeros(num_tiles + 1, np.int64)
    g_offsets = np.zeros(n + 1, np.int64)
    for g in range(n):
        x0, y0, x1, y1 = boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3]
        if x1 < x0 or y1 < y0:
            continue
        for ty in range(y0 // TILE, y1 // TILE + 1):
            for tx in range(x0 // TILE, x1 // TILE + 1):
                offsets[ty * tiles_x + tx + 1] += 1
        g_offsets[g + 1] = (y1 // TILE - y0 // TILE + 1) * (x1 // TILE - x0 // TILE + 1)
    for t in range(num_tiles):
        offsets[t + 1] += offsets[t]
    for g in range(n):
        g_offsets[g + 1] += g_offsets[g]
    ids = np.empty(offsets[num_tiles], np.int64)
    slot = np.empty(offsets[num_tiles], np.int64)
    cursor = offsets[:num_tiles].copy()
    record_offsets = np.zeros(num_tiles + 1, np.int64)  # room for every pixel of each entry's box in its tile
    for i in range(order.shape[0]):  # the drawn Gaussians (or all), front to back
        g = order[i]
        x0, y0, x1, y1 = boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3]
        if x1 < x0 or y1 < y0:
            continue
        s = g_offsets[g]
        for ty in range(
            y0 // TILE, y1 // TILE + 1
        ):  # the Gaussian's tiles in increasing t: its entries in increasing order
            for tx in range(x0 // TILE, x1 // TILE + 1):
                t = ty * tiles_x + tx
                ids[cursor[t]] = g
                slot[cursor[t]] = s
                s += 1
                cursor[t] += 1
                record_offsets[t + 1] += (min(x1, tx * TILE + TILE - 1) - max(x0, tx * TILE) + 1) * (
                    min(y1, ty * TILE + TILE - 1) - max(y0, ty * TILE) + 1
                )
    tile_order, worker_offsets = partition(record_offsets[1:], num_workers)
    for t in range(num_tiles):
        record_offsets[t + 1] += record_offsets[t]
    return offsets, ids, g_offsets, slot, record_offsets, tile_order, worker_offsets


@njit(cache=True)
def partition(work, num_workers):
    """The tiles split among the threads by their estimated work (largest first, each to the least loaded thread):
    worker w blends tiles tile_order[worker_offsets[w]:worker_offsets[w + 1]]. The kernels run prange over the
    workers (numba gives each thread one), so no thread waits on another's busier block of tiles; which thread
    blends a tile changes no result."""
    num_tiles = work.shape[0]
    by_work = np.argsort(-work, kind="mergesort")
    load = np.zeros(num_workers, np.int64)
    owner = np.empty(num_tiles, np.int64)
    counts = np.zeros(num_workers + 1, np.int64)
    for i in range(num_tiles):
        w = np.argmin(load)
        owner[i] = w
        load[w] += work[by_work[i]] + 1
        counts[w + 1] += 1
    for w in range(num_workers):
        counts[w + 1] += counts[w]
    tile_order = np.empty(num_tiles, np.int64)
    cursor = counts[:num_workers].copy()
    for i in range(num_tiles):
        tile_order[cursor[owner[i]]] = by_work[i]
        cursor[owner[i]] += 1
    return tile_order, counts


@njit(cache=True, inline="always")
def _row_span(cx, cy, b, a, det, a_r2, row_f, half, zero, width_f):
    """Columns [first, last] (as floats, clamped to [-1, width]) whose pixel centres lie in the footprint ellipse
    on the row with top y = row_f: the torch backend's `ellipse_pixel_pairs` (touch="centre"), operation for
    operation and in the same order, so both backends round alike and test the same pixels."""
    top = row_f - cy
    dy = top + half
    inner = a_r2 - det * dy * dy
    if inner < zero:
        inner = zero
    half_span = np.sqrt(inner) / a
    shift = cx - b * dy / a
    first = np.ceil((shift - half_span) - half)
    last = np.floor((shift + half_span) - half)
    minus_one = zero - (half + half)
    if first < minus_one:
        first = minus_one
    if last > width_f:
        last = width_f
    return first, last


@njit(cache=True, inline="always")
def _tile_bounds(t, tiles_x, width, height):
    """Tile t's first pixel column and row and its last ones (inclusive; tiles at the image's edge are cut)."""
    x_start, y_start = (t % tiles_x) * TILE, (t // tiles_x) * TILE
    return x_start, y_start, min(x_start + TILE, width) - 1, min(y_start + TILE, height) - 1


@njit(cache=True, inline="always")
def _footprint(means2d, conics, opacities, g):
    """Gaussian g's centre, conic and opacity as scalars (mx, my, a, b, c, opacity), so that the tile loops keep
    them in registers over all its pixels."""
    return means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g]


@njit(cache=True, inline="always")
def _row_walk(mx, my, a, b, hc, det, a_r2, boxes, g, row, x_start, x_end, y_start, grid, half, zero, width_f):
    """One row of Gaussian g's footprint within a tile, as both tile loops walk it: the columns [col_lo, col_hi]
    whose pixel centres lie in the footprint ellipse (`_row_span`), clipped to the box and the tile (empty:
    col_lo > col_hi), the row's offset dy from the centre with the exponent's terms b dy and c dy^2 / 2 (hc = c / 2),
    and `base`, the tile-buffer index of the row's column 0 (pixel col is base + col)."""
    row_f = grid[row]
    first, last_col = _row_span(mx, my, b, a, det[g], a_r2[g], row_f, half, zero, width_f)
    if not first <= last_col:
        return 1, 0, zero, zero, zero, 0
    dy = (row_f + half) - my
    return (
        max(int(first), boxes[g, 0], x_start),
        min(int(last_col), boxes[g, 2], x_end),
        dy,
        b * dy,
        hc * dy * dy,
        (row - y_start) * TILE - x_start,
    )


@njit(cache=True, inline="always")
def _pixel_response(grid, col, half, mx, ha, bdy, cdy):
    """On the row `_row_walk` set up (bdy = b dy, cdy = c dy^2 / 2; ha = a / 2): the offset dx of pixel col's centre
    from the Gaussian's and the response exp(-d^T conic d / 2) there, one arrangement of the exponent for both tile
    loops, so that the reverse pass meets the forward's hits to the bit."""
    dx = (grid[col] + half) - mx
    return dx, np.exp(-(dx * (ha * dx + bdy) + cdy))


@njit(cache=True, parallel=True)
def forward(
    means2d,
    conics,
    opacities,
    values,
    det,
    a_r2,
    boxes,
    offsets,
    ids,
    tile_order,
    worker_offsets,
    height,
    width,
    tiles_x,
    grid,
    consts,
    min_transmittance,
    record_offsets,
    rec_pixel,
    rec_response,
    entry_end,
):
    """Blend every tile front to back. Returns the image [H, W, K], each pixel's transmittance after its last
    blended hit (float64) and that hit's entry index (-1: none), and the number of blended hits per tile.
    The last value column is alpha's constant 1: its channel is written as 1 - T (the sum of the weights).

    Within a tile the loop runs over its Gaussians in depth order and, for each, over the pixels whose centres
    lie in its footprint ellipse (the torch backend's candidate pairs); per-pixel state (transmittance, sums,
    stopped) lives in tile-sized buffers, so each pixel still sees its hits front to back. Thread w blends the
    tiles tile_order[worker_offsets[w]:worker_offsets[w + 1]] (`partition`) with its own buffers.

    With record arrays (rec_pixel non-empty), each blended hit is also written down in blending order: its pixel in
    the tile and its response exp(-d^T conic d / 2), at record_offsets[t] onwards; entry_end[e] is where entry e's
    hits end (they start where the previous entry of the tile ends). `backward_recorded` reads them back."""
    k_values = values.shape[1]
    k_sums = k_values - 1  # alpha's channel is 1 - T
    num_tiles = offsets.shape[0] - 1
    half, min_alpha, max_alpha, zero = consts[0], consts[1], consts[2], consts[3]
    width_f = grid[width]
    image = np.empty((height, width, k_values), values.dtype)
    final_t = np.empty((height, width), np.float64)
    last_entry = np.empty((height, width), np.int64)
    tile_hits = np.zeros(num_tiles, np.int64)
    recording = rec_pixel.shape[0] > 0
    for w in prange(worker_offsets.shape[0] - 1):
        acc = np.empty((TILE * TILE, max(k_sums, 1)), np.float64)  # float64 sums: rounding stays far below 1e-5
        # the transmittance as a float64 product of (1 - alpha): the torch backend's exp of a float64 sum of float32
        # log(1 - alpha) to ~1e-7, without a log and an exp per hit
        trans = np.empty(TILE * TILE, np.float64)
        last = np.empty(TILE * TILE, np.int64)
        stopped = np.empty(TILE * TILE, np.bool_)
        row_stopped = np.empty(TILE, np.int64)  # stopped pixels per row: a row whose pixels all stopped is skipped
        for i in range(worker_offsets[w], worker_offsets[w + 1]):
            t = tile_order[i]
            x_start, y_start, x_end, y_end = _tile_bounds(t, tiles_x, width, height)
            pixels = (x_end - x_start + 1) * (y_end - y_start + 1)
            acc[:] = 0.0
            trans[:] = 1.0
            last[:] = -1
            stopped[:] = False
            row_stopped[:] = 0
            row_width = x_end - x_start + 1
            num_stopped = 0
            hits = 0
            cursor = record_offsets[t]
            if recording:
                for e in range(offsets[t], offsets[t + 1]):
                    entry_end[e] = cursor  # entries after an early end of the tile record nothing
            for e in range(offsets[t], offsets[t + 1]):
                g = ids[e]
                mx, my, a, b, c, opacity = _footprint(means2d, conics, opacities, g)
                ha, hc = half * a, half * c
                for row in range(max(boxes[g, 1], y_start), min(boxes[g, 3], y_end) + 1):
                    if row_stopped[row - y_start] == row_width:
                        continue
                    col_lo, col_hi, dy, bdy, cdy, base = _row_walk(
                        mx, my, a, b, hc, det, a_r2, boxes, g, row, x_start, x_end, y_start, grid, half, zero, width_f
                    )
                    for col in range(col_lo, col_hi + 1):
                        p = base + col
                        if stopped[p]:
                            continue
                        dx, response = _pixel_response(grid, col, half, mx, ha, bdy, cdy)
                        raw = opacity * response
                        if not raw >= min_alpha:  # as torch's `raw >= min_alpha`: a NaN is skipped too
                            continue
                        alpha = min(raw, max_alpha)
                        after = trans[p] * (1.0 - np.float64(alpha))
                        if after < min_transmittance:  # 3DGS's early stop: this hit and all after it are dropped
                            stopped[p] = True
                            row_stopped[row - y_start] += 1
                            num_stopped += 1
                            continue
                        weight = alpha * values.dtype.type(trans[p])
                        for k in range(k_sums):
                            acc[p, k] += weight * values[g, k]
                        trans[p] = after
                        last[p] = e
                        hits += 1
                        if recording:
                            rec_pixel[cursor] = p
                            rec_response[cursor] = response
                            cursor += 1
                if recording:
                    entry_end[e] = cursor
                if num_stopped == pixels:
                    break
            tile_hits[t] = hits
            for row in range(y_start, y_end + 1):
                for col in range(x_start, x_end + 1):
                    p = (row - y_start) * TILE + (col - x_start)
                    for k in range(k_sums):
                        image[row, col, k] = acc[p, k]
                    image[row, col, k_sums] = 1.0 - trans[p]
                    final_t[row, col] = trans[p]
                    last_entry[row, col] = last[p]
    return image, final_t, last_entry, tile_hits


@njit(cache=True, inline="always")
def _hit_gradients(trans, behind, p, raw, response, max_alpha, dx, dy, a, b, c, value, grad, grad_values, sums):
    """One blended hit of the reverse pass (both backward kernels): the pixel's transmittance in front of the hit
    recovered (trans[p]), S of the pixel (behind[p]) and the value gradients (grad_values) updated in place; returns
    the entry's sums (x, y, a, b, c, opacity, |x|, |y|) with this hit's share added. value: the Gaussian's [K] values,
    grad: the pixel's [K] output gradient."""
    g_x, g_y, g_a, g_b, g_c, g_o, abs_x, abs_y = sums
    alpha = min(raw, max_alpha)
    keep = 1.0 / (1.0 - np.float64(alpha))
    trans[p] *= keep
    transmittance = value.dtype.type(trans[p])
    weight = alpha * transmittance
    q = 0.0  # dL/dweight = <dL/dout, value>
    for k in range(value.shape[0]):
        q += grad[k] * value[k]
        grad_values[k] += grad[k] * weight
    grad_alpha = transmittance * q - behind[p] * keep
    behind[p] += weight * q
    if raw <= max_alpha:  # a clamped alpha does not move with the Gaussian
        grad_exponent = grad_alpha * alpha  # d(o G)/d(exponent) = o G
        grad_x = grad_exponent * (a * dx + b * dy)
        grad_y = grad_exponent * (b * dx + c * dy)
        g_x += grad_x
        g_y += grad_y
        g_a -= 0.5 * grad_exponent * dx * dx
        g_b -= grad_exponent * dx * dy
        g_c -= 0.5 * grad_exponent * dy * dy
        g_o += grad_alpha * response
        abs_x += abs(grad_x)  # each pixel's own gradient, as gsplat's absgrad
        abs_y += abs(grad_y)
    return g_x, g_y, g_a, g_b, g_c, g_o, abs_x, abs_y


@njit(cache=True, inline="always")
def _store_entry(entry_grads, r, sums, grad_values):
    g_x, g_y, g_a, g_b, g_c, g_o, abs_x, abs_y = sums
    entry_grads[r, 0], entry_grads[r, 1], entry_grads[r, 2], entry_grads[r, 3] = g_x, g_y, g_a, g_b
    entry_grads[r, 4], entry_grads[r, 5], entry_grads[r, 6], entry_grads[r, 7] = g_c, g_o, abs_x, abs_y
    for k in range(grad_values.shape[0]):
        entry_grads[r, PER_ENTRY + k] = grad_values[k]


@njit(cache=True, parallel=True)
def backward(
    means2d,
    conics,
    opacities,
    values,
    det,
    a_r2,
    boxes,
    offsets,
    ids,
    tile_order,
    worker_offsets,
    height,
    width,
    tiles_x,
    grid,
    consts,
    slot,
    final_t,
    last_entry,
    grad_image,
):
    """The reverse pass, tile by tile: each tile's Gaussians back to front, each pixel's transmittance in front of
    a hit recovered from the one behind it, T_k = T_(k+1) / (1 - alpha_k) (float64: alpha <= max_alpha and
    T >= min_transmittance, so a few hundred divisions lose nothing near 1e-5), and S = sum of alpha_j T_j q_j
    over the hits behind.
    Gradients go to one row per (tile, Gaussian) entry [E, 8 + K], entry e's at row slot[e]; `reduce_entries` sums
    them per Gaussian in a fixed order, so the result does not depend on how tiles were spread over threads."""
    k_values = values.shape[1]
    half, min_alpha, max_alpha, zero = consts[0], consts[1], consts[2], consts[3]
    width_f = grid[width]
    entry_grads = np.zeros((ids.shape[0], PER_ENTRY + k_values), values.dtype)
    for w in prange(worker_offsets.shape[0] - 1):
        trans = np.empty(TILE * TILE, np.float64)
        behind = np.empty(TILE * TILE, np.float64)  # S of each pixel
        last = np.empty(TILE * TILE, np.int64)
        row_last = np.empty(TILE, np.int64)  # the last entry any pixel of the row blended: rows past it are skipped
        grad_values = np.empty(k_values, np.float64)
        for i in range(worker_offsets[w], worker_offsets[w + 1]):
            t = tile_order[i]
            x_start, y_start, x_end, y_end = _tile_bounds(t, tiles_x, width, height)
            behind[:] = 0.0
            row_last[:] = -1
            for row in range(y_start, y_end + 1):
                for col in range(x_start, x_end + 1):
                    p = (row - y_start) * TILE + (col - x_start)
                    trans[p] = final_t[row, col]
                    last[p] = last_entry[row, col]
                    row_last[row - y_start] = max(row_last[row - y_start], last[p])
            tile_last = (
                row_last.max()
            )  # entries behind every pixel's last hit (the far side of an object) are not visited
            for e in range(min(offsets[t + 1] - 1, tile_last), offsets[t] - 1, -1):
                g = ids[e]
                mx, my, a, b, c, opacity = _footprint(means2d, conics, opacities, g)
                ha, hc = half * a, half * c
                # this entry's sums in locals (registers), not an array: they are added to at every hit
                sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                grad_values[:] = 0.0
                for row in range(max(boxes[g, 1], y_start), min(boxes[g, 3], y_end) + 1):
                    if e > row_last[row - y_start]:
                        continue
                    col_lo, col_hi, dy, bdy, cdy, base = _row_walk(
                        mx, my, a, b, hc, det, a_r2, boxes, g, row, x_start, x_end, y_start, grid, half, zero, width_f
                    )
                    for col in range(col_lo, col_hi + 1):
                        p = base + col
                        if e > last[p]:  # behind the pixel's last blended hit (or the pixel blended nothing)
                            continue
                        dx, response = _pixel_response(grid, col, half, mx, ha, bdy, cdy)
                        raw = opacity * response
                        if not raw >= min_alpha:  # as torch's `raw >= min_alpha`: a NaN is skipped too
                            continue
                        sums = _hit_gradients(
                            trans,
                            behind,
                            p,
                            raw,
                            response,
                            max_alpha,
                            dx,
                            dy,
                            a,
                            b,
                            c,
                            values[g],
                            grad_image[row, col],
                            grad_values,
                            sums,
                        )
                _store_entry(entry_grads, slot[e], sums, grad_values)
    return entry_grads


@njit(cache=True, parallel=True)
def reduce_entries(entry_grads, g_offsets):
    """Per Gaussian, the sum of its entries' gradients (rows g_offsets[g] to g_offsets[g + 1], in increasing entry
    order; see bin_tiles' slot) in float64: [N, 8 + K]."""
    n = g_offsets.shape[0] - 1
    width = entry_grads.shape[1]
    out = np.zeros((n, width), np.float64)
    for g in prange(n):
        for r in range(g_offsets[g], g_offsets[g + 1]):
            for k in range(width):
                out[g, k] += entry_grads[r, k]
    return out


# floating-point reassociation and contraction for the recorded backward only: it decides no hit (the forward's record
# does), so only the gradients' last bits move (held to 1e-4 of torch's); the code, and so the bits, stay the same for
# any thread count. No nnan/ninf: the comparisons keep their IEEE meaning.
GRADIENT_MATH = {"reassoc", "contract", "arcp", "nsz"}


@njit(cache=True, parallel=True, fastmath=GRADIENT_MATH)
def backward_recorded(
    means2d,
    conics,
    opacities,
    values,
    offsets,
    ids,
    tile_order,
    worker_offsets,
    width,
    height,
    tiles_x,
    grid,
    consts,
    slot,
    final_t,
    record_offsets,
    rec_pixel,
    rec_response,
    entry_end,
    grad_image,
):
    """`backward` from the forward's record of the blended hits: the same arithmetic per hit, without finding the
    pixels again (row spans, the alpha test) or recomputing exp, and only over hits that were blended. The tiles
    are split among the threads by the forward's hits per tile (`partition`)."""
    k_values = values.shape[1]
    half, max_alpha = consts[0], consts[2]
    entry_grads = np.empty((ids.shape[0], PER_ENTRY + k_values), values.dtype)
    for w in prange(worker_offsets.shape[0] - 1):
        trans = np.empty(TILE * TILE, np.float64)
        behind = np.empty(TILE * TILE, np.float64)  # S of each pixel
        grad_tile = np.empty((TILE * TILE, k_values), values.dtype)
        grad_values = np.empty(k_values, np.float64)
        for i in range(worker_offsets[w], worker_offsets[w + 1]):
            t = tile_order[i]
            x_start, y_start, x_end, y_end = _tile_bounds(t, tiles_x, width, height)
            behind[:] = 0.0
            for row in range(y_start, y_end + 1):
                for col in range(x_start, x_end + 1):
                    p = (row - y_start) * TILE + (col - x_start)
                    trans[p] = final_t[row, col]
                    for k in range(k_values):
                        grad_tile[p, k] = grad_image[row, col, k]
            for e in range(offsets[t + 1] - 1, offsets[t] - 1, -1):
                start = entry_end[e - 1] if e > offsets[t] else record_offsets[t]
                g = ids[e]
                sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                grad_values[:] = 0.0
                if entry_end[e] > start:
                    mx, my, a, b, c, opacity = _footprint(means2d, conics, opacities, g)
                    for r in range(start, entry_end[e]):  # one hit per pixel: any order
                        p = np.int64(rec_pixel[r])
                        response = rec_response[r]
                        dx = (grid[x_start + p % TILE] + half) - mx
                        dy = (grid[y_start + p // TILE] + half) - my
                        sums = _hit_gradients(
                            trans,
                            behind,
                            p,
                            opacity * response,
                            response,
                            max_alpha,
                            dx,
                            dy,
                            a,
                            b,
                            c,
                            values[g],
                            grad_tile[p],
                            grad_values,
                            sums,
                        )
                _store_entry(entry_grads, slot[e], sums, grad_values)  # every row written (np.empty above)
    return entry_grads
