"""The compiled projection of backend `numba` (matspray.render.numba.backend): what `project_gaussians` and
`rasterize._setup` compute for backend torch (centres, conics, depths, footprint boxes, radii), per Gaussian in
one loop, and its hand-written backward.

The forward repeats the torch code's float32 operations in the same order (matrix products summed left to right,
as torch's CPU matmul and einsum do for these sizes, no fused multiply-adds), so both backends project to the
same bits and draw the same pixels: tests/test_numba_backend.py checks it. Constants come in `consts`, an array of
the inputs' float type, because numba promotes float32 arithmetic with a Python number to float64 (as in
kernels). The scales come in already exponentiated and the opacities already squashed (torch's exp and
sigmoid, whose results numba's libm would differ from in the last bit for about 1 % of inputs), and the radii
are left to torch (its float32 sqrt differs from a correctly rounded one in the last bit for ~15 % of them).
Only the footprint margin's log and the boxes' sqrt are numba's: a last-bit difference there can only move a box
edge by a pixel whose centre is outside the footprint (alpha below min_alpha), which changes no drawn pixel.

The backward runs in float64 and follows torch's autograd through the same expressions, `torch.where` and
clamps included (no gradient through a clamped Jacobian direction or through a replaced depth or determinant).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from matspray.render.numba.kernels import njit

# indices into `consts`
NEAR, EPS2D, LIM_X_LO, LIM_X_HI, LIM_Y_LO, LIM_Y_HI, FX, FY, CX, CY = range(10)
DET_REL, DET_FLOOR, MIN_ALPHA, MARGIN, HALF, THREE, ONE, TWO, ZERO, WIDTH, HEIGHT, NORM_EPS, CONIC_FLOOR = range(10, 23)
NUM_CONSTS = 23


@njit(cache=True, parallel=True)
def project(means, scales, quats, opacities, view, consts):
    """Per Gaussian (view: [3, 4] world to camera): means2d [N, 2], conics [N, 3], depths [N] (camera z),
    cov2d [N, 3], pixel boxes [N, 4] int64 (x0, y0, x1, y1; empty: 0, 0, -1, -1), and the footprint terms of the tile
    loops, det [N] = max(a c - b^2, floor) and a_r2 [N] = a * radius2, radius2 = 2 ln(opacity / min_alpha) + 1e-3;
    flags [N] for backward."""
    n = means.shape[0]
    dtype = means.dtype
    means2d = np.empty((n, 2), dtype)
    conics = np.empty((n, 3), dtype)
    depths = np.empty(n, dtype)
    cov2d = np.empty((n, 3), dtype)
    boxes = np.empty((n, 4), np.int64)
    det_out = np.empty(n, dtype)
    a_r2 = np.empty(n, dtype)
    flags = np.empty(n, np.int8)  # bit 0: in front of the near plane; bit 1: and a regular footprint; bit 2: drawn
    zero, one, two, half = consts[ZERO], consts[ONE], consts[TWO], consts[HALF]
    fx, fy, cx, cy = consts[FX], consts[FY], consts[CX], consts[CY]
    for g in prange(n):
        cam0 = ((means[g, 0] * view[0, 0] + means[g, 1] * view[0, 1]) + means[g, 2] * view[0, 2]) + view[0, 3]
        cam1 = ((means[g, 0] * view[1, 0] + means[g, 1] * view[1, 1]) + means[g, 2] * view[1, 2]) + view[1, 3]
        cam2 = ((means[g, 0] * view[2, 0] + means[g, 1] * view[2, 1]) + means[g, 2] * view[2, 2]) + view[2, 3]
        depths[g] = cam2
        valid = cam2 > consts[NEAR]
        z = cam2 if valid else one
        x, y = cam0 / z, cam1 / z
        mx, my = fx * x + cx, fy * y + cy
        means2d[g, 0], means2d[g, 1] = mx, my
        xc = max(min(x, consts[LIM_X_HI]), -consts[LIM_X_LO])
        yc = max(min(y, consts[LIM_Y_HI]), -consts[LIM_Y_LO])
        rot = _rotation(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3], one, two, consts[NORM_EPS])
        fxz, fyz = fx / z, fy / z
        cxx = cxy = cyy = zero
        for k in range(3):  # column k of W L and of the two rows of J W L
            lk0, lk1, lk2 = rot[k] * scales[g, k], rot[3 + k] * scales[g, k], rot[6 + k] * scales[g, k]
            w0 = (view[0, 0] * lk0 + view[0, 1] * lk1) + view[0, 2] * lk2
            w1 = (view[1, 0] * lk0 + view[1, 1] * lk1) + view[1, 2] * lk2
            w2 = (view[2, 0] * lk0 + view[2, 1] * lk1) + view[2, 2] * lk2
            rx, ry = fxz * (w0 - xc * w2), fyz * (w1 - yc * w2)
            # torch sums the three products left to right, starting from the first (not from 0)
            if k == 0:
                cxx, cxy, cyy = rx * rx, rx * ry, ry * ry
            else:
                cxx, cxy, cyy = cxx + rx * rx, cxy + rx * ry, cyy + ry * ry
        cxx, cyy = cxx + consts[EPS2D], cyy + consts[EPS2D]
        det = cxx * cyy - cxy * cxy
        in_front = valid
        valid = valid and det > consts[DET_REL] * max(abs(cxx * cyy), consts[DET_FLOOR])
        flags[g] = (1 if in_front else 0) + (2 if valid else 0)
        if not valid:
            det = one
        a, b, c = cyy / det, -cxy / det, cxx / det
        conics[g, 0], conics[g, 1], conics[g, 2] = a, b, c
        # the footprint: where opacity * exp(-q / 2) >= min_alpha, q <= radius2 (with a margin; the exact alpha
        # test of the tile loops decides). numba's log may differ from torch's in the last bit: that moves the
        # margin by ~1e-7 px, where alpha is already below min_alpha, so no drawn pixel changes
        ratio = max(opacities[g] / consts[MIN_ALPHA], one)
        radius2 = two * np.log(ratio) + consts[MARGIN]
        hx, hy = np.sqrt(radius2 * cxx), np.sqrt(radius2 * cyy)
        x0, y0 = max(np.ceil((mx - hx) - half), zero), max(np.ceil((my - hy) - half), zero)
        x1, y1 = (
            min(np.floor((mx + hx) - half), consts[WIDTH] - one),
            min(np.floor((my + hy) - half), consts[HEIGHT] - one),
        )
        finite = np.isfinite(mx - hx) and np.isfinite(my - hy) and np.isfinite(mx + hx) and np.isfinite(my + hy)
        drawn = valid and opacities[g] >= consts[MIN_ALPHA] and finite and x0 <= x1 and y0 <= y1
        if drawn:
            boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = int(x0), int(y0), int(x1), int(y1)
            flags[g] += 4
        else:
            boxes[g, 0], boxes[g, 1], boxes[g, 2], boxes[g, 3] = 0, 0, -1, -1
        cov2d[g, 0], cov2d[g, 1], cov2d[g, 2] = cxx, cxy, cyy
        det_out[g] = max(a * c - b * b, consts[CONIC_FLOOR])
        a_r2[g] = a * radius2
    return means2d, conics, depths, cov2d, boxes, det_out, a_r2, flags


@njit(cache=True, inline="always")
def _rotation(w, x, y, z, one, two, norm_eps):
    """matspray.gaussians.quaternion_to_matrix(F.normalize(q)), operation for operation; row-major, as a tuple
    (no allocation per Gaussian)."""
    norm = max(np.sqrt(((w * w + x * x) + y * y) + z * z), norm_eps)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    return (
        one - two * (y * y + z * z),
        two * (x * y - w * z),
        two * (x * z + w * y),
        two * (x * y + w * z),
        one - two * (x * x + z * z),
        two * (y * z - w * x),
        two * (x * z - w * y),
        two * (y * z + w * x),
        one - two * (x * x + y * y),
    )


@njit(
    cache=True, parallel=True, fastmath={"reassoc", "contract", "arcp", "nsz"}
)  # decides nothing: only last bits move
def project_backward(means, scales, quats, view, consts, flags, grad_means2d, grad_conics, grad_depths):
    """d loss / d (means [N, 3], scales [N, 3], quats [N, 4]) from d loss / d (means2d, conics, depths), computed in
    float64; `flags` is the forward's (bit 0: in front of the near plane, bit 1: its determinant test too)."""
    n = means.shape[0]
    grad_means = np.zeros((n, 3), means.dtype)
    grad_scales = np.zeros((n, 3), means.dtype)
    grad_quats = np.zeros((n, 4), means.dtype)
    v = view.astype(np.float64)
    eps2d, fx, fy = np.float64(consts[EPS2D]), np.float64(consts[FX]), np.float64(consts[FY])
    lxl, lxh = np.float64(consts[LIM_X_LO]), np.float64(consts[LIM_X_HI])
    lyl, lyh = np.float64(consts[LIM_Y_LO]), np.float64(consts[LIM_Y_HI])
    chunk = 256  # Gaussians per parallel step: the scratch arrays below are allocated once per chunk
    for first in prange((n + chunk - 1) // chunk):
        wl = np.empty((3, 3))  # W L, row i
        g_wl = np.empty((3, 3))
        vx, vy, rx, ry, s = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
        for g in range(first * chunk, min(first * chunk + chunk, n)):
            gmx, gmy = np.float64(grad_means2d[g, 0]), np.float64(grad_means2d[g, 1])
            ga, gb, gc = np.float64(grad_conics[g, 0]), np.float64(grad_conics[g, 1]), np.float64(grad_conics[g, 2])
            gd = np.float64(grad_depths[g])
            if gmx == 0.0 and gmy == 0.0 and ga == 0.0 and gb == 0.0 and gc == 0.0 and gd == 0.0:
                continue  # drawn nowhere: every gradient is 0 (most of a large scene's Gaussians in one view)
            valid_z, det_ok = (flags[g] & 1) != 0, (flags[g] & 2) != 0
            m0, m1, m2 = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
            cam0 = v[0, 0] * m0 + v[0, 1] * m1 + v[0, 2] * m2 + v[0, 3]
            cam1 = v[1, 0] * m0 + v[1, 1] * m1 + v[1, 2] * m2 + v[1, 3]
            cam2 = v[2, 0] * m0 + v[2, 1] * m1 + v[2, 2] * m2 + v[2, 3]
            z = cam2 if valid_z else 1.0
            inv_z = 1.0 / z  # reciprocals: float64 has digits to spare, and divisions dominate this loop
            x, y = cam0 * inv_z, cam1 * inv_z
            xc, yc = min(max(x, -lxl), lxh), min(max(y, -lyl), lyh)
            qw, qx, qy, qz = (
                np.float64(quats[g, 0]),
                np.float64(quats[g, 1]),
                np.float64(quats[g, 2]),
                np.float64(quats[g, 3]),
            )
            norm = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            inv_norm = 1.0 / max(norm, 1e-12)
            w, qa, qb, qc = qw * inv_norm, qx * inv_norm, qy * inv_norm, qz * inv_norm
            rot = _unit_rotation(w, qa, qb, qc)
            fxz, fyz = fx * inv_z, fy * inv_z
            for k in range(3):
                s[k] = scales[g, k]
                for i in range(3):
                    wl[i, k] = (v[i, 0] * rot[k] + v[i, 1] * rot[3 + k] + v[i, 2] * rot[6 + k]) * s[k]
                vx[k], vy[k] = wl[0, k] - xc * wl[2, k], wl[1, k] - yc * wl[2, k]
                rx[k], ry[k] = fxz * vx[k], fyz * vy[k]
            cxx = rx[0] * rx[0] + rx[1] * rx[1] + rx[2] * rx[2] + eps2d
            cxy = rx[0] * ry[0] + rx[1] * ry[1] + rx[2] * ry[2]
            cyy = ry[0] * ry[0] + ry[1] * ry[1] + ry[2] * ry[2] + eps2d
            if det_ok:
                inv_det = 1.0 / (cxx * cyy - cxy * cxy)
                g_det = -(ga * cyy - gb * cxy + gc * cxx) * inv_det * inv_det
                g_cxx, g_cyy, g_cxy = (
                    gc * inv_det + g_det * cyy,
                    ga * inv_det + g_det * cxx,
                    -gb * inv_det - 2.0 * g_det * cxy,
                )
            else:  # the forward replaced det by 1
                g_cxx, g_cyy, g_cxy = gc, ga, -gb
            g_z = 0.0
            g_xc = g_yc = 0.0
            for k in range(3):
                g_rx = 2.0 * g_cxx * rx[k] + g_cxy * ry[k]
                g_ry = 2.0 * g_cyy * ry[k] + g_cxy * rx[k]
                g_z -= (g_rx * rx[k] + g_ry * ry[k]) * inv_z  # through fx / z and fy / z
                g_vx, g_vy = fxz * g_rx, fyz * g_ry
                g_wl[0, k], g_wl[1, k], g_wl[2, k] = g_vx, g_vy, -xc * g_vx - yc * g_vy
                g_xc -= g_vx * wl[2, k]
                g_yc -= g_vy * wl[2, k]
            g_x = fx * gmx + _clamp_share(x, -lxl, lxh) * g_xc
            g_y = fy * gmy + _clamp_share(y, -lyl, lyh) * g_yc
            g_cam0, g_cam1 = g_x * inv_z, g_y * inv_z
            g_z -= (g_x * x + g_y * y) * inv_z
            g_cam2 = gd + (g_z if valid_z else 0.0)  # the replaced depth takes no gradient
            for j in range(3):
                grad_means[g, j] = v[0, j] * g_cam0 + v[1, j] * g_cam1 + v[2, j] * g_cam2
            # d/d L = W^T d/d(W L); then L = rot diag(s)
            g00 = g01 = g02 = g10 = g11 = g12 = g20 = g21 = g22 = 0.0
            for k in range(3):
                l0 = v[0, 0] * g_wl[0, k] + v[1, 0] * g_wl[1, k] + v[2, 0] * g_wl[2, k]
                l1 = v[0, 1] * g_wl[0, k] + v[1, 1] * g_wl[1, k] + v[2, 1] * g_wl[2, k]
                l2 = v[0, 2] * g_wl[0, k] + v[1, 2] * g_wl[1, k] + v[2, 2] * g_wl[2, k]
                grad_scales[g, k] = l0 * rot[k] + l1 * rot[3 + k] + l2 * rot[6 + k]
                if k == 0:
                    g00, g10, g20 = l0 * s[0], l1 * s[0], l2 * s[0]
                elif k == 1:
                    g01, g11, g21 = l0 * s[1], l1 * s[1], l2 * s[1]
                else:
                    g02, g12, g22 = l0 * s[2], l1 * s[2], l2 * s[2]
            gw = 2.0 * (-qc * g01 + qb * g02 + qc * g10 - qa * g12 - qb * g20 + qa * g21)
            gx = 2.0 * (qb * g01 + qc * g02 + qb * g10 - 2.0 * qa * g11 - w * g12 + qc * g20 + w * g21 - 2.0 * qa * g22)
            gy = 2.0 * (
                -2.0 * qb * g00 + qa * g01 + w * g02 + qa * g10 + qc * g12 - w * g20 + qc * g21 - 2.0 * qb * g22
            )
            gz = 2.0 * (
                -2.0 * qc * g00 - w * g01 + qa * g02 + w * g10 - 2.0 * qc * g11 + qb * g12 + qa * g20 + qb * g21
            )
            if norm > 1e-12:  # through q / |q|: only the direction moves the rotation
                dot = w * gw + qa * gx + qb * gy + qc * gz
                grad_quats[g, 0], grad_quats[g, 1] = (gw - w * dot) * inv_norm, (gx - qa * dot) * inv_norm
                grad_quats[g, 2], grad_quats[g, 3] = (gy - qb * dot) * inv_norm, (gz - qc * dot) * inv_norm
            else:  # q / 1e-12
                grad_quats[g, 0], grad_quats[g, 1], grad_quats[g, 2], grad_quats[g, 3] = (
                    gw * 1e12,
                    gx * 1e12,
                    gy * 1e12,
                    gz * 1e12,
                )
    return grad_means, grad_scales, grad_quats


@njit(cache=True, inline="always")
def _unit_rotation(w, x, y, z):
    """quaternion_to_matrix of a unit quaternion, row-major, in float64 (backward's)."""
    return (
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@njit(cache=True, inline="always")
def _clamp_share(value, lo, hi):
    """The share of d/d(clamped) that torch.maximum(torch.minimum(value, hi), lo) passes to value: 1 inside,
    half on a bound (torch splits a tie), 0 outside."""
    if lo < value < hi:
        return 1.0
    if value == lo or value == hi:
        return 0.5
    return 0.0


def depth_order(depths: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """The drawn Gaussians (non-empty boxes), nearest centre first; equal depths in index order (a stable sort).
    Backend torch orders equal depths as torch.argsort leaves them (unspecified): two Gaussians at exactly the
    same depth covering the same pixel may blend in the other order there."""
    if depths.dtype == np.float32:  # a radix sort of the float bits, faster than numba's mergesort (docs/defaults.md)
        return _radix_order(depths.view(np.uint32), boxes)
    return _merge_order(depths, boxes)


@njit(cache=True)
def _drawn(boxes):
    drawn = np.empty(boxes.shape[0], np.int64)
    count = 0
    for g in range(boxes.shape[0]):
        if boxes[g, 2] >= boxes[g, 0]:
            drawn[count] = g
            count += 1
    return drawn[:count]


@njit(cache=True)
def _merge_order(depths, boxes):
    drawn = _drawn(boxes)
    return drawn[np.argsort(depths[drawn], kind="mergesort")]


@njit(cache=True)
def _radix_order(bits, boxes):
    """Stable LSD radix sort (3 passes of 11 bits) of float32 keys given as their bits: flipping all bits of a
    negative float and the sign bit of a positive one makes the unsigned order the float order."""
    ids = _drawn(boxes)
    n = ids.shape[0]
    keys = np.empty(n, np.uint32)
    for i in range(n):
        b = bits[ids[i]]
        keys[i] = ~b if b >> np.uint32(31) else b | np.uint32(0x80000000)
    other_ids, other_keys = np.empty_like(ids), np.empty_like(keys)
    counts = np.empty(2049, np.int64)
    for shift in (0, 11, 22):
        counts[:] = 0
        for i in range(n):
            counts[((keys[i] >> np.uint32(shift)) & np.uint32(2047)) + 1] += 1
        for d in range(2048):
            counts[d + 1] += counts[d]
        for i in range(n):
            d = (keys[i] >> np.uint32(shift)) & np.uint32(2047)
            other_ids[counts[d]], other_keys[counts[d]] = ids[i], keys[i]
            counts[d] += 1
        ids, other_ids = other_ids, ids
        keys, other_keys = other_keys, keys
    return ids
