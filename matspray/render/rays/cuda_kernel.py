"""The numba.cuda kernel of `cuda_rays` (its own module: numba's CUDA simulator, which the tests on the CPU use, finds
`cuda` among a kernel's module globals)."""

import math

import numpy

if not hasattr(numpy, "row_stack"):  # removed in NumPy 2.5; the GPU image's numba-cuda still names it when it loads
    numpy.row_stack = numpy.vstack

from numba import cuda  # noqa: E402 (after the alias above)


@cuda.jit(fastmath=False)
def response(a, origin, opacities, owner, pixel_ids, width, k, sub_x, sub_y, scale, alphas, depths):
    # one thread per (pair, sub-pixel ray); a pair's k^2 rays are neighbours, so their frame reads are shared
    i = cuda.grid(1)
    samples = sub_x.shape[0]
    if i >= alphas.shape[0] * samples:
        return
    p = i // samples
    s = i - p * samples
    g = owner[p]
    pixel = pixel_ids[p]
    row = pixel // width
    corner_x = (float(pixel - row * width) - k[2]) / k[0]  # (column - cx) / fx
    corner_y = (float(row) - k[3]) / k[1]
    # d0 = A[:, 0] corner_x + A[:, 1] corner_y + A[:, 2]; ax = A[:, 0]; ay = A[:, 1] (whitened frame)
    d0x = a[g, 0, 0] * corner_x + a[g, 0, 1] * corner_y + a[g, 0, 2]
    d0y = a[g, 1, 0] * corner_x + a[g, 1, 1] * corner_y + a[g, 1, 2]
    d0z = a[g, 2, 0] * corner_x + a[g, 2, 1] * corner_y + a[g, 2, 2]
    axx, axy, axz = a[g, 0, 0], a[g, 1, 0], a[g, 2, 0]
    ayx, ayy, ayz = a[g, 0, 1], a[g, 1, 1], a[g, 2, 1]
    ox, oy, oz = origin[g, 0], origin[g, 1], origin[g, 2]
    u, v = sub_x[s], sub_y[s]
    od = (ox * d0x + oy * d0y + oz * d0z) + (ox * axx + oy * axy + oz * axz) * u
    od = od + (ox * ayx + oy * ayy + oz * ayz) * v
    dd = (d0x * d0x + d0y * d0y + d0z * d0z) + (2 * (d0x * axx + d0y * axy + d0z * axz)) * u
    dd = dd + (2 * (d0x * ayx + d0y * ayy + d0z * ayz)) * v
    dd = dd + (axx * axx + axy * axy + axz * axz) * (u * u)
    dd = dd + (2 * (axx * ayx + axy * ayy + axz * ayz)) * (u * v)
    dd = dd + (ayx * ayx + ayy * ayy + ayz * ayz) * (v * v)
    tau = -od / dd
    mahalanobis2 = max((ox * ox + oy * oy + oz * oz) + od * tau, 0.0)
    alphas[p, s] = opacities[g] * math.exp(scale * mahalanobis2)
    depths[p, s] = tau
