"""Bilinear lookup in a small image at many points, with a backward pass that scales on a GPU.

`F.grid_sample`'s backward adds each point's gradient into the four texels around it by atomic adds. Refinement
looks up environment maps of a few hundred texels at every pixel of a view (a quarter of a million points), so on
a GPU those adds queue on the same few addresses (docs/dev/gpu.md measures what that cost). `bilinear_sample` gives the
same values and gradients as `grid_sample` (bilinear, border padding, align_corners=True), but its backward adds
into `replicas` copies of the image, point p into copy p % replicas, and sums the copies after: the same sums in
another order, each address shared by a few points instead of thousands.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

POINTS_PER_ADDRESS = 8  # the replicas are as many as keep about this many points on each texel of a copy


def grid_sample_border(image: Tensor, grid: Tensor) -> Tensor:  # [1, C, h, w], [P, 2] -> [C, P]
    out = F.grid_sample(image, grid.view(1, 1, -1, 2), mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(image.shape[1], -1)


def _axis(coordinate: Tensor, size: int) -> tuple[Tensor, Tensor, Tensor]:
    """grid_sample's texel coordinate along one axis of `size` texels (align_corners=True, clamped to the border),
    split into the lower texel and the fraction, and d(texel coordinate) / d(grid coordinate): 0 where the border
    clamps, and on the border itself, which grid_sample counts as outside. Python scalars only, no host copies: this
    runs inside CUDA graph captures."""
    scale = (size - 1) / 2.0
    raw = (coordinate + 1.0) * scale
    slope = ((raw > 0) & (raw < size - 1)) * scale
    clamped = raw.clamp(0.0, size - 1)
    lower = clamped.floor()
    return lower.long(), clamped - lower, slope


def _corners(grid: Tensor, height: int, width: int):
    """The four corners (nw, ne, sw, se) of each point: flat texel indices [4, P] (clamped into the image), their
    bilinear weights [4, P] (0 for a corner outside the image, which grid_sample reads as 0), whether each is inside
    [4, P], the fractions fx, fy [P] and the slopes of `_axis` [P] each."""
    x0, fx, slope_x = _axis(grid[:, 0], width)
    y0, fy, slope_y = _axis(grid[:, 1], height)
    xs, ys = torch.stack([x0, x0 + 1, x0, x0 + 1]), torch.stack([y0, y0, y0 + 1, y0 + 1])  # [4, P]
    inside = (xs < width) & (ys < height)
    weights = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])  # [4, P]
    index = ys.clamp_max(height - 1) * width + xs.clamp_max(width - 1)
    return index, weights * inside, inside, fx, fy, slope_x, slope_y


class _BilinearSample(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: Tensor, grid: Tensor, replicas: int) -> Tensor:  # [1, C, h, w], [P, 2] -> [C, P]
        ctx.save_for_backward(image, grid)
        ctx.replicas = replicas
        return grid_sample_border(image, grid)

    @staticmethod
    def backward(ctx, grad: Tensor):  # [C, P]
        image, grid = ctx.saved_tensors
        channels, height, width = image.shape[1:]
        index, weights, inside, fx, fy, slope_x, slope_y = _corners(grid, height, width)
        texels = height * width
        grad_image = grad_grid = None
        if ctx.needs_input_grad[0]:
            replicas = ctx.replicas
            points = grid.shape[0]
            copy = torch.arange(points, device=grid.device) % replicas  # [P]
            target = (copy * texels + index).flatten()  # [4 P]
            added = (grad[:, None, :] * weights[None]).reshape(channels, -1)  # [C, 4 P]
            copies = grad.new_zeros(channels, replicas * texels).index_add_(1, target, added)
            grad_image = copies.view(channels, replicas, texels).sum(1).view(1, channels, height, width)
        if ctx.needs_input_grad[1]:
            values = image.reshape(channels, texels)[:, index] * inside  # [C, 4, P], 0 outside
            nw, ne, sw, se = values.unbind(1)
            d_x = ((ne - nw) * (1 - fy) + (se - sw) * fy).mul(grad).sum(0)  # [P]
            d_y = ((sw - nw) * (1 - fx) + (se - ne) * fx).mul(grad).sum(0)
            grad_grid = torch.stack([d_x * slope_x, d_y * slope_y], dim=-1)  # [P, 2]
        return grad_image, grad_grid, None


def replicas_for(points: int, texels: int) -> int:
    return max(1, points // (POINTS_PER_ADDRESS * texels))


def bilinear_sample(image: Tensor, grid: Tensor, replicas: int | None = None) -> Tensor:  # [1, C, h, w], [P, 2]
    """`grid_sample` (bilinear, border, align_corners=True) of `image` at `grid`, as [C, P], by the spread
    backward (module docstring); `replicas` None: enough for about POINTS_PER_ADDRESS adds per texel."""
    if replicas is None:
        replicas = replicas_for(grid.shape[0], image.shape[-2] * image.shape[-1])
    return _BilinearSample.apply(image, grid, replicas)
