"""The texture lookup of the renderer and of the ground truth: bilinear between texel centres, with
glTF's wrap modes per axis (as Mitsuba's bitmap texture with filter 'bilinear' and a `wrap_mode`)."""

from __future__ import annotations

import torch
from torch import Tensor

WRAPS = ("repeat", "clamp", "mirror")


def wrap_index(index: Tensor, size: int, mode: str) -> Tensor:  # [...] int64 -> [...] in [0, size)
    if mode == "repeat":
        return torch.remainder(index, size)
    if mode == "clamp":
        return index.clamp(0, size - 1)
    if mode == "mirror":  # ... 1 0 | 0 1 ... size-1 | size-1 ... (OpenGL MIRRORED_REPEAT on texel indices)
        period = torch.remainder(index, 2 * size)
        return torch.where(period >= size, 2 * size - 1 - period, period)
    raise ValueError(f"unknown wrap mode '{mode}' (valid: {', '.join(WRAPS)})")


def apply_uv_transform(uv: Tensor, matrix: Tensor | None) -> Tensor:  # [N, 2], [3, 3] -> [N, 2]
    if matrix is None:
        return uv
    matrix = matrix.to(uv)
    return uv @ matrix[:2, :2].T + matrix[:2, 2]


def sample_texture(
    image: Tensor,  # [H, W, C]; row 0 at v = 0
    uv: Tensor,  # [N, 2]
    wrap_s: str = "repeat",
    wrap_t: str = "repeat",
    uv_transform: Tensor | None = None,  # [3, 3] affine applied to uv first (KHR_texture_transform)
) -> Tensor:  # [N, C]
    """Bilinear lookup with texel centres at (i + 0.5) / size."""
    height, width = image.shape[:2]
    uv = apply_uv_transform(uv.to(image.dtype if image.is_floating_point() else torch.float64), uv_transform)
    x = uv[:, 0] * width - 0.5
    y = uv[:, 1] * height - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    wx, wy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.long(), y0.long()
    xs = (wrap_index(x0, width, wrap_s), wrap_index(x0 + 1, width, wrap_s))
    ys = (wrap_index(y0, height, wrap_t), wrap_index(y0 + 1, height, wrap_t))
    top = image[ys[0], xs[0]] * (1 - wx) + image[ys[0], xs[1]] * wx
    bottom = image[ys[1], xs[0]] * (1 - wx) + image[ys[1], xs[1]] * wx
    return top * (1 - wy) + bottom * wy
