"""A view's blend matrix (every blended (Gaussian, pixel) hit and its weight alpha * T, by pixel then Gaussian) on
backend `numba`: what frozen views (matspray.render.raster.gbuffer) build once per training view, and what
`rasterize.view_weights` and `gbuffer.sorted_pairs` make with torch. The torch version builds every candidate pair
as a tensor and sorts them; here the compiled forward blends once with its record of hits (pixel and response, in
blending order: kernels.forward; backend.numba_view_blend), and `recorded_blend` replays the record tile by tile to
turn each hit into its weight, with the forward's arithmetic (float32 alpha, float64 transmittance), and places it
in its pixel's row. The hits are the forward's, which are the torch backend's (kernels._row_span).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from matspray.render.numba.kernels import TILE, njit


@njit(cache=True, inline="always")
def _entry_hits(t, e, offsets, record_offsets, entry_end):
    """The record's rows of tile t's entry e: they follow the previous entry's (an entry after the tile's early end
    has an empty range: its end is the tile's start)."""
    return range(entry_end[e - 1] if e > offsets[t] else record_offsets[t], entry_end[e])


@njit(cache=True, parallel=True)
def recorded_blend(
    ids, offsets, opacities, record_offsets, rec_pixel, rec_response, entry_end, tiles_x, width, height, consts
):
    """The view's blend matrix [pixels, Gaussians] from the forward's record, in CSR order (by pixel, row-major over
    the image, then by Gaussian): row pointers crow [P + 1], columns [M] and weights [M] (float32); with each
    Gaussian's coverage [N] (float32: its weights summed in blending order, tile by tile, as `index_add_` over the
    hits in record order sums them) and its number of hits [N].

    A pixel belongs to one tile, so the tiles run in parallel while they count their pixels' hits and while they
    place them, each tile's entries in increasing Gaussian id, so that each pixel's row comes out in Gaussian order
    without a sort. Only the coverage, whose Gaussians span tiles, is summed in one thread. consts: [2] max_alpha
    (kernels' layout)."""
    num_tiles, n, pixels = offsets.shape[0] - 1, opacities.shape[0], width * height
    max_alpha = consts[2]
    rec_weight = np.empty(rec_pixel.shape[0], opacities.dtype)
    per_pixel = np.zeros(pixels + 1, np.int64)
    for t in prange(num_tiles):  # each hit's weight, and each pixel's count of hits
        trans = np.ones(TILE * TILE, np.float64)
        x_start, y_start = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        for e in range(offsets[t], offsets[t + 1]):
            g = ids[e]
            for h in _entry_hits(t, e, offsets, record_offsets, entry_end):
                p = rec_pixel[h]
                alpha = min(opacities[g] * rec_response[h], max_alpha)
                rec_weight[h] = alpha * opacities.dtype.type(trans[p])
                trans[p] = trans[p] * (1.0 - np.float64(alpha))
                per_pixel[(y_start + p // TILE) * width + x_start + p % TILE + 1] += 1
    crow = np.cumsum(per_pixel)
    columns = np.empty(crow[pixels], np.int64)
    weights = np.empty(crow[pixels], opacities.dtype)
    for t in prange(num_tiles):  # each hit to its pixel's row, the tile's entries taken in Gaussian order
        x_start, y_start = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        cursor = np.empty(TILE * TILE, np.int64)
        for p in range(TILE * TILE):
            row, col = y_start + p // TILE, x_start + p % TILE
            cursor[p] = crow[row * width + col] if row < height and col < width else 0
        for k in np.argsort(ids[offsets[t] : offsets[t + 1]]):  # a Gaussian has one entry per tile
            e = offsets[t] + k
            for h in _entry_hits(t, e, offsets, record_offsets, entry_end):
                p = rec_pixel[h]
                columns[cursor[p]], weights[cursor[p]] = ids[e], rec_weight[h]
                cursor[p] += 1
    coverage = np.zeros(n, opacities.dtype)
    hits = np.zeros(n, np.int64)
    for t in range(num_tiles):
        for e in range(offsets[t], offsets[t + 1]):
            g = ids[e]
            for h in _entry_hits(t, e, offsets, record_offsets, entry_end):
                coverage[g] += rec_weight[h]
                hits[g] += 1
    return crow, columns, weights, coverage, hits
