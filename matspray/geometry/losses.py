"""Training losses of the geometry stage. Images are [H, W, C]; colours are sRGB-encoded in [0, 1]."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2


def gaussian_taps(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> Tensor:  # [size]
    offsets = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    taps = torch.exp(-offsets**2 / (2 * sigma**2))
    return taps / taps.sum()


def ssim(pred: Tensor, target: Tensor) -> Tensor:  # [H, W, C] x2 -> scalar
    """Differentiable SSIM for training (as 3DGS): 11-tap Gaussian window, sigma 1.5, zero padding
    ('same' size), averaged over pixels and channels."""
    taps = gaussian_taps(dtype=pred.dtype, device=pred.device)
    channels = pred.shape[-1]
    x = torch.stack([pred, target, pred * pred, target * target, pred * target]).permute(0, 3, 1, 2)  # [5, C, H, W]
    x = x.reshape(1, 5 * channels, *x.shape[2:])
    pad = taps.numel() // 2
    x = F.conv2d(x, taps.view(1, 1, 1, -1).expand(5 * channels, 1, 1, -1), padding=(0, pad), groups=5 * channels)
    x = F.conv2d(x, taps.view(1, 1, -1, 1).expand(5 * channels, 1, -1, 1), padding=(pad, 0), groups=5 * channels)
    mu_x, mu_y, xx, yy, xy = x.reshape(5, channels, *x.shape[2:])
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    value = ((2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)) / ((mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2))
    return value.mean()


def photometric_loss(pred: Tensor, target: Tensor, ssim_weight: float) -> Tensor:  # [H, W, 3] x2 -> scalar
    """(1 - w) L1 + w (1 - SSIM), the 3DGS loss (w = 0.2)."""
    return (1 - ssim_weight) * (pred - target).abs().mean() + ssim_weight * (1 - ssim(pred, target))


def flatten_loss(log_scales: Tensor) -> Tensor:  # [N, 3] -> scalar
    """Mean ratio of each Gaussian's shortest to its middle axis: 0 for discs, 1 for balls."""
    ordered = torch.sort(log_scales, dim=-1).values
    return torch.exp(ordered[:, 0] - ordered[:, 1]).mean()


def normal_consistency_loss(
    rendered: Tensor,  # [H, W, 3] blended Gaussian normals (not unit)
    from_depth: Tensor,  # [H, W, 3] unit normals of the rendered depth
    weights: Tensor,  # [H, W] where (and how much) the surface counts
) -> Tensor:  # scalar: weighted mean of 1 - cos(angle)
    cos = (F.normalize(rendered, dim=-1) * from_depth).sum(-1)
    return ((1 - cos) * weights).sum() / weights.sum().clamp_min(1e-6)
