"""Lifting's ray tracing in compiled loops, for backend numba: what `matspray.method.lift.lift_view` reads of a view,
the (Gaussian, pixel, inside the core) entries and how many of the pixel's sub-pixel rays made each, without listing
the hits.

The torch tracer (`matspray.render.rays.contributions`, the readable reference, whose docstring has the equations)
enumerates (Gaussian, pixel) candidates, evaluates every sub-pixel ray of each, sorts all hits of a band of rows
by ray and depth, composites them with segmented sums, and `lift_view` then collapses the hits into entries with
a sort of its own. Here the image is cut into 16 x 16 pixel tiles; each tile's Gaussians (those whose silhouette
box meets it, `kernels.bin_tiles`) are tested against each pixel's rays, each ray's hits are sorted and
composited on the spot, and each pixel's entries are counted as its rays are. A first, cheap pass counts each
pixel's candidates (the silhouettes' row spans only), which bounds its entries (two per candidate), so the
tracing pass writes every pixel's entries at a known place, once.

Float64 as the torch tracer, with its candidates (`pairs.ellipse_pixel_pairs`, touch="area") and its operations
in its order, so both find the same hits; the transmittance is a running product here (a sum of logs there),
which differs by rounding only. Tests compare the entries with the torch path's on random scenes.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import prange

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.numba.kernels import TILE, bin_tiles, njit
from matspray.render.numba.threads import threads
from matspray.render.rays.contributions import ray_setup
from matspray.render.settings import RasterSettings

MAX_BAND_ENTRIES = 1 << 24  # bound of a band's entries (16 bytes each), so that large images trace in bands


@njit(cache=True, inline="always")
def _row_columns(boxes, silhouettes, g, row, width):
    """Columns [first, last] of row `row` whose pixel areas meet Gaussian g's silhouette (empty: first > last):
    the torch tracer's candidates (`pairs.ellipse_pixel_pairs`, touch="area", radius 1), operation for operation;
    the whole box row for an unbounded silhouette."""
    x0, y0, x1, y1 = boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3]
    if row < y0 or row > y1 or x1 < x0:
        return 1, 0
    if silhouettes[g, 5] != 0.0:
        return x0, x1
    cx, cy, a, b, c = silhouettes[g, 0], silhouettes[g, 1], silhouettes[g, 2], silhouettes[g, 3], silhouettes[g, 4]
    det = max(a * c - b * b, 1e-30)
    top = row - cy
    reach = math.sqrt(1.0 * a / det)
    lo, hi = max(top, -reach), min(top + 1.0, reach)
    dy_right = -b * math.sqrt(1.0 / (c * det))
    dy_left = min(max(-dy_right, lo), hi)
    dy_right = min(max(dy_right, lo), hi)
    x_lo = cx - b * dy_left / a - math.sqrt(max(a * 1.0 - det * dy_left * dy_left, 0.0)) / a
    x_hi = cx - b * dy_right / a + math.sqrt(max(a * 1.0 - det * dy_right * dy_right, 0.0)) / a
    first = max(int(max(math.floor(x_lo), -1.0)), x0)
    last = min(int(min(math.floor(x_hi), float(width))), x1)
    return first, last


@njit(cache=True, parallel=True)
def count_candidates(boxes, silhouettes, offsets, ids, tiles_x, tiles_y, width, height, on_object):
    """[H * W] int64: the candidates of each pixel on the object (0 elsewhere)."""
    counts = np.zeros(width * height, np.int64)
    for t in prange(tiles_x * tiles_y):
        tx, ty = t % tiles_x, t // tiles_x
        for py in range(ty * TILE, min(ty * TILE + TILE, height)):
            for e in range(offsets[t], offsets[t + 1]):
                first, last = _row_columns(boxes, silhouettes, ids[e], py, width)
                for px in range(max(first, tx * TILE), min(last, tx * TILE + TILE - 1) + 1):
                    if on_object[py * width + px]:
                        counts[py * width + px] += 1
    return counts


@njit(cache=True, parallel=True)
def trace_entries(
    A,  # [N, 3, 3] float64 camera -> whitened frame
    origin,  # [N, 3] float64 camera centre in the whitened frame
    opacities,  # [N] float64
    core_alphas,  # [N] float32 alpha at the footprint's edge: a hit at or above it is inside the core
    boxes,  # [N, 4] int64 (x0, y0, x1, y1) pixels whose area meets the silhouette; empty: x1 < x0
    silhouettes,  # [N, 6] float64 centre x, y, conic a, b, c, unbounded (1.0: its box is the whole image)
    offsets,  # [T + 1] int64 tile lists (bin_tiles, by Gaussian id)
    ids,  # [E] int64
    tiles_x,
    ty0,  # the band's tile rows [ty0, ty1)
    ty1,
    width,
    height,
    s,  # sub-pixel rays per side
    camera,  # [4] float64 fx, fy, cx, cy
    params,  # [6] float64 falloff, min_alpha, near, max_alpha, min_transmittance, visibility_threshold
    on_object,  # [H * W] bool: pixels whose rays count
    starts,  # [H * W] int64 where each pixel's entries go (two per candidate)
    out_keys,  # [M] int64 (Gaussian * H * W + pixel) * 2 + inside the core
    out_counts,  # [M] int64 rays of the pixel that made the entry
    filled,  # [H * W] int64 entries each pixel wrote
):
    fx, fy, cx, cy = camera[0], camera[1], camera[2], camera[3]
    falloff, min_alpha, near, max_alpha = params[0], params[1], params[2], params[3]
    min_t, visibility_threshold = params[4], params[5]
    ss = s * s
    n_pixels = width * height
    sub = (np.arange(s) + 0.5) / s
    sub_x, sub_y = sub / fx, sub / fy  # the direction's offsets, as the torch tracer divides them
    mid_x, mid_y = 0.5 / fx, 0.5 / fy  # to the pixel's centre
    for k in prange((ty1 - ty0) * tiles_x):
        t = ty0 * tiles_x + k
        tx, ty = t % tiles_x, t // tiles_x
        first, last = offsets[t], offsets[t + 1]
        n_c = last - first
        if n_c == 0:
            continue
        # per ray, its hits' sort keys: the bits of the float32 depth (positive floats order as their bits, which is
        # how the torch tracer sorts) above the candidate's place c in the tile list, which runs by Gaussian id, so
        # ties go to the lower id, as there; the hit's alpha is kept at [ray, c]
        hit_key = np.empty((ss, n_c), np.int64)
        hit_alpha = np.empty((ss, n_c), np.float64)
        n_hits = np.zeros(ss, np.int64)
        depth32 = np.empty(1, np.float32)
        depth_bits = depth32.view(np.int32)
        span_lo = np.empty(n_c, np.int64)
        span_hi = np.empty(n_c, np.int64)
        # the pixel's candidates, front to back by their depth on the ray through the pixel's centre: its rays then
        # meet their hits nearly in order, and the insertion sort per ray moves few of them
        pixel_c = np.empty(n_c, np.int64)
        pixel_tau = np.empty(n_c, np.float64)
        in_core = np.zeros(n_c, np.int64)  # the pixel's rays that hit candidate c, inside its core / outside
        outside = np.zeros(n_c, np.int64)
        for py in range(ty * TILE, min(ty * TILE + TILE, height)):
            corner_y = (py - cy) / fy
            for c in range(n_c):
                span_lo[c], span_hi[c] = _row_columns(boxes, silhouettes, ids[first + c], py, width)
            for px in range(tx * TILE, min(tx * TILE + TILE, width)):
                pixel = py * width + px
                if not on_object[pixel]:
                    continue
                corner_x = (px - cx) / fx
                n_candidates = 0
                for c in range(n_c):
                    if span_lo[c] <= px <= span_hi[c]:
                        g = ids[first + c]
                        dx = A[g, 0, 0] * (corner_x + mid_x) + A[g, 0, 1] * (corner_y + mid_y) + A[g, 0, 2]
                        dy = A[g, 1, 0] * (corner_x + mid_x) + A[g, 1, 1] * (corner_y + mid_y) + A[g, 1, 2]
                        dz = A[g, 2, 0] * (corner_x + mid_x) + A[g, 2, 1] * (corner_y + mid_y) + A[g, 2, 2]
                        od = origin[g, 0] * dx + origin[g, 1] * dy + origin[g, 2] * dz
                        tau = -od / (dx * dx + dy * dy + dz * dz)
                        i = n_candidates
                        while i > 0 and pixel_tau[i - 1] > tau:
                            pixel_tau[i], pixel_c[i] = pixel_tau[i - 1], pixel_c[i - 1]
                            i -= 1
                        pixel_tau[i], pixel_c[i] = tau, c
                        n_candidates += 1
                n_hits[:] = 0
                for i in range(n_candidates):
                    c = pixel_c[i]
                    g = ids[first + c]
                    o0, o1, o2 = origin[g, 0], origin[g, 1], origin[g, 2]
                    # d' = d0 + u ax + v ay: the torch tracer's terms, in its order
                    d0x = A[g, 0, 0] * corner_x + A[g, 0, 1] * corner_y + A[g, 0, 2]
                    d0y = A[g, 1, 0] * corner_x + A[g, 1, 1] * corner_y + A[g, 1, 2]
                    d0z = A[g, 2, 0] * corner_x + A[g, 2, 1] * corner_y + A[g, 2, 2]
                    axx, axy, axz = A[g, 0, 0], A[g, 1, 0], A[g, 2, 0]
                    ayx, ayy, ayz = A[g, 0, 1], A[g, 1, 1], A[g, 2, 1]
                    od0 = o0 * d0x + o1 * d0y + o2 * d0z
                    oax = o0 * axx + o1 * axy + o2 * axz
                    oay = o0 * ayx + o1 * ayy + o2 * ayz
                    dd0 = d0x * d0x + d0y * d0y + d0z * d0z
                    d0ax2 = 2 * (d0x * axx + d0y * axy + d0z * axz)
                    d0ay2 = 2 * (d0x * ayx + d0y * ayy + d0z * ayz)
                    axax = axx * axx + axy * axy + axz * axz
                    axay2 = 2 * (axx * ayx + axy * ayy + axz * ayz)
                    ayay = ayx * ayx + ayy * ayy + ayz * ayz
                    oo = o0 * o0 + o1 * o1 + o2 * o2
                    # squared distance where alpha falls to min_alpha, with room for rounding: the alpha test decides
                    reach2 = 2.0 * math.log(max(opacities[g] / min_alpha, 1.0)) / falloff * (1.0 + 1e-9) + 1e-12
                    for iy in range(s):
                        v = sub_y[iy]
                        for ix in range(s):
                            u = sub_x[ix]
                            od = od0 + oax * u + oay * v
                            dd = dd0 + d0ax2 * u + d0ay2 * v + axax * (u * u) + axay2 * (u * v) + ayay * (v * v)
                            tau = -od / dd
                            m2 = max(oo + od * tau, 0.0)
                            if m2 > reach2:  # alpha < min_alpha by far: no exp
                                continue
                            alpha = opacities[g] * math.exp(-0.5 * falloff * m2)
                            if alpha >= min_alpha and tau > near:
                                r = iy * s + ix
                                hit_alpha[r, c] = alpha
                                depth32[0] = tau
                                hit_key[r, n_hits[r]] = (np.int64(depth_bits[0]) << 32) | c
                                n_hits[r] += 1
                for r in range(ss):
                    keys = hit_key[r]
                    for i in range(1, n_hits[r]):  # insertion sort, nearly in order already
                        key = keys[i]
                        j = i
                        while j > 0 and keys[j - 1] > key:
                            keys[j] = keys[j - 1]
                            j -= 1
                        keys[j] = key
                    transmittance = 1.0  # a float64 product (the torch tracer sums logs: the same to rounding)
                    for i in range(n_hits[r]):
                        c = keys[i] & 0xFFFFFFFF
                        alpha = min(hit_alpha[r, c], max_alpha)
                        behind = transmittance * (1.0 - alpha)
                        if behind < min_t:  # 3DGS's early stop: this hit and all behind it go
                            break
                        if transmittance >= visibility_threshold:
                            if np.float32(alpha) >= core_alphas[ids[first + c]]:  # compared in float32, as lift_view
                                in_core[c] += 1
                            else:
                                outside[c] += 1
                        transmittance = behind
                cursor = starts[pixel]
                for i in range(n_candidates):
                    c = pixel_c[i]
                    key = (ids[first + c] * n_pixels + pixel) * 2
                    if in_core[c] > 0:
                        out_keys[cursor], out_counts[cursor] = key + 1, in_core[c]
                        cursor += 1
                        in_core[c] = 0
                    if outside[c] > 0:
                        out_keys[cursor], out_counts[cursor] = key, outside[c]
                        cursor += 1
                        outside[c] = 0
                filled[pixel] = cursor - starts[pixel]


@njit(cache=True)
def compact(keys, counts, starts, filled):
    """The pixels' entries one after another (each pixel's region [starts, starts + filled) of `keys`, `counts`)."""
    total = 0
    for p in range(filled.shape[0]):
        total += filled[p]
    out_keys = np.empty(total, np.int64)
    out_counts = np.empty(total, np.int64)
    cursor = 0
    for p in range(filled.shape[0]):
        for i in range(starts[p], starts[p] + filled[p]):
            out_keys[cursor], out_counts[cursor] = keys[i], counts[i]
            cursor += 1
    return out_keys, out_counts


def tile_row_bands(candidates: np.ndarray, width: int, height: int, budget: int) -> list[tuple[int, int]]:
    """Bands of whole tile rows [ty0, ty1) whose entries (two per candidate) stay within `budget`, at least one tile
    row each."""
    tiles_y = -(-height // TILE)
    per_row = [2 * int(candidates[ty * TILE * width : (ty + 1) * TILE * width].sum()) for ty in range(tiles_y)]
    bands, start, total = [], 0, 0
    for ty, entries in enumerate(per_row):
        if ty > start and total + entries > budget:
            bands.append((start, ty))
            start, total = ty, 0
        total += entries
    bands.append((start, tiles_y))
    return bands


def lift_entries(
    A: torch.Tensor,  # [N, 3, 3] float64
    origin: torch.Tensor,  # [N, 3] float64
    opacities: torch.Tensor,  # [N] float64
    core_alphas: torch.Tensor,  # [N] float32
    boxes: torch.Tensor,  # [N, 4] long
    silhouettes: torch.Tensor,  # [N, 6] float64 centre x, y, conic a, b, c, unbounded
    on_object: torch.Tensor,  # [H * W] bool
    width: int,
    height: int,
    s: int,
    K: torch.Tensor,  # [3, 3]
    params: tuple[float, ...],  # falloff, min_alpha, near, max_alpha, min_transmittance, visibility_threshold
    budget: int | None = None,  # entries per band (default MAX_BAND_ENTRIES)
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry keys [M] ((Gaussian * H * W + pixel) * 2 + inside the core) and their ray counts [M], each key once."""
    A_np, origin_np, opacities_np = (x.contiguous().numpy() for x in (A, origin, opacities))
    core_np, boxes_np, shapes_np = (x.contiguous().numpy() for x in (core_alphas, boxes, silhouettes))
    on_object_np = on_object.contiguous().numpy()
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    offsets, ids = bin_tiles(boxes_np, np.arange(len(boxes_np), dtype=np.int64), tiles_x, tiles_y, 1)[:2]
    camera = np.array([float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])
    parts = []
    with threads():
        candidates = count_candidates(boxes_np, shapes_np, offsets, ids, tiles_x, tiles_y, width, height, on_object_np)
        for ty0, ty1 in tile_row_bands(candidates, width, height, budget or MAX_BAND_ENTRIES):
            pixels = slice(ty0 * TILE * width, min(ty1 * TILE, height) * width)
            starts = np.zeros(width * height, np.int64)
            starts[pixels] = np.cumsum(2 * candidates[pixels]) - 2 * candidates[pixels]
            room = int(2 * candidates[pixels].sum())
            keys, counts = np.empty(room, np.int64), np.empty(room, np.int64)
            filled = np.zeros(width * height, np.int64)
            trace_entries(
                A_np, origin_np, opacities_np, core_np, boxes_np, shapes_np, offsets, ids, tiles_x, ty0, ty1,
                width, height, s, camera, np.array(params, np.float64), on_object_np, starts, keys, counts, filled,
            )  # fmt: skip
            parts.append(compact(keys, counts, starts[pixels], filled[pixels]))
    keys, counts = (torch.from_numpy(np.concatenate([part[i] for part in parts])) for i in range(2))
    return keys, counts


def trace_view(
    gaussians: Gaussians,
    camera: Camera,
    on_object: torch.Tensor,  # [H * W] bool: pixels whose rays count
    samples_per_side: int,
    core_alphas: torch.Tensor,  # [N] float32: a hit at or above it is inside the Gaussian's core
    falloff: float,
    settings: RasterSettings,
    visibility_threshold: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`lift_entries` of `camera`'s view of the Gaussians (CPU): entry keys [M] and ray counts [M]."""
    frame, opacities, silhouettes = ray_setup(gaussians, camera, falloff, settings)
    shapes = torch.cat(
        [silhouettes.centres, silhouettes.conics, silhouettes.unbounded[:, None].to(silhouettes.centres)], dim=1
    ).double()  # [N, 6]
    params = (falloff, settings.min_alpha, settings.near, settings.max_alpha, settings.min_transmittance)
    return lift_entries(
        *frame, opacities, core_alphas.float(), silhouettes.boxes, shapes, on_object, camera.width, camera.height,
        samples_per_side, camera.K.double(), (*params, visibility_threshold),
    )  # fmt: skip
