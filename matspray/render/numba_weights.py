"""A view's blending weights (every blended (Gaussian, pixel) hit and its weight alpha * T) on backend `numba`: what
`rasterize.view_weights` computes with torch, which frozen views (matspray.render.gbuffer) need once per training
view. The torch version builds every candidate pair as a tensor; here the compiled forward blends once with its
record of hits (pixel and response, in blending order: numba_kernels.forward), and `recorded_weights` replays the
record tile by tile to turn each hit into its weight, with the forward's arithmetic (float32 alpha, float64
transmittance). The hits are the forward's, which are the torch backend's (numba_kernels._row_span).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import prange
from torch import Tensor

from matspray.render.numba_kernels import TILE, njit
from matspray.render.numba_threads import threads
from matspray.render.settings import RasterSettings


@njit(cache=True, parallel=True)
def recorded_weights(
    ids, offsets, opacities, record_offsets, rec_pixel, rec_response, entry_end, tiles_x, width, consts
):
    """Per recorded hit h (record_offsets[t] <= h < entry_end of the tile's last entry): its Gaussian, its pixel
    (row-major over the image) and its weight; `valid[h]` is False where the tile's room held no hit.
    consts: [2] max_alpha (numba_kernels' layout)."""
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


def numba_view_weights(gaussians, camera, settings: RasterSettings = RasterSettings()) -> tuple[Tensor, Tensor, Tensor]:
    """`rasterize.view_weights` on backend numba: Gaussian ids [M], row-major pixel ids [M], weights [M]; None when
    the forward's record would pass numba_backend.RECORD_BUDGET (the torch version does those)."""
    from matspray.render import numba_backend as backend
    from matspray.render.backend import note_render

    note_render("numba")
    backend.ensure_compiled(np.float32)  # (its warm-up compiles `recorded_weights` too)
    layout = backend._Layout(camera, settings, np.float32)
    opacities = backend._numpy(gaussians.opacities.detach().float(), np.float32)
    arrays = [
        backend._numpy(t.detach().float(), np.float32) for t in (gaussians.means, gaussians.scales, gaussians.quats)
    ]
    with threads():
        means2d, conics, depths, cov2d, boxes, det, a_r2, flags = backend.projection().project(
            *arrays, opacities, layout.view, layout.consts
        )
    layout.footprints(boxes, det, a_r2, depths, cov2d, flags)
    room = int(layout.record_offsets[-1])
    if room > backend.RECORD_BUDGET:
        return None
    record = (np.empty(room, np.uint8), np.empty(room, np.float32), np.empty(len(layout.ids), np.int64))
    values = np.ones((len(opacities), 1), np.float32)  # alpha's channel only
    with threads():
        backend.kernels().forward(
            *layout.common(means2d, conics, opacities, values), layout.min_transmittance, layout.record_offsets, *record
        )
        gaussian, pixel, weight, valid = recorded_weights(
            layout.ids,
            layout.offsets,
            opacities,
            layout.record_offsets,
            *record,
            layout.tiles_x,
            layout.width,
            layout.blend_consts,
        )
    return tuple(torch.from_numpy(column[valid]) for column in (gaussian, pixel, weight))
