"""A view's blending weights (every blended (Gaussian, pixel) hit and its weight alpha * T) on backend `numba`: what
`rasterize.view_weights` computes with torch, which frozen views (matspray.render.raster.gbuffer) need once per training
view. The torch version builds every candidate pair as a tensor; here the compiled forward blends once with its
record of hits (pixel and response, in blending order: kernels.forward; backend.numba_view_weights),
and `recorded_weights` replays the record tile by tile to turn each hit into its weight, with the forward's
arithmetic (float32 alpha, float64 transmittance). The hits are the forward's, which are the torch backend's
(kernels._row_span).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from matspray.render.numba.kernels import TILE, njit


@njit(cache=True, parallel=True)
def recorded_weights(
    ids, offsets, opacities, record_offsets, rec_pixel, rec_response, entry_end, tiles_x, width, consts
):
    """Per recorded hit h (record_offsets[t] <= h < entry_end of the tile's last entry): its Gaussian, its pixel
    (row-major over the image) and its weight; `valid[h]` is False where the tile's room held no hit.
    consts: [2] max_alpha (kernels' layout)."""
    room = rec_pixel.shape[0]
    gaussian = np.empty(room, np.int64)
    pixel = np.empty(room, np.int64)
    weight = np.empty(room, opacities.dtype)
    valid = np.zeros(room, np.bool_)
    max_alpha = consts[2]
    for t in prange(offsets.shape[0] - 1):
        trans = np.ones(TILE * TILE, np.float64)
        x_start, y_start = (t % tiles_x) * TILE, (t // tiles_x) * TILE
        start = record_offsets[t]
        for e in range(offsets[t], offsets[t + 1]):
            g = ids[e]
            for h in range(start, entry_end[e]):
                p = rec_pixel[h]
                alpha = min(opacities[g] * rec_response[h], max_alpha)
                weight[h] = alpha * opacities.dtype.type(trans[p])
                trans[p] = trans[p] * (1.0 - np.float64(alpha))
                gaussian[h] = g
                pixel[h] = (y_start + p // TILE) * width + x_start + p % TILE
                valid[h] = True
            start = entry_end[e]
    return gaussian, pixel, weight, valid
