"""Training losses of the geometry stage. Images are [H, W, C]; colours are sRGB-encoded in [0, 1]."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.metrics import ssim_loss


def photometric_loss(pred: Tensor, target: Tensor, ssim_weight: float) -> Tensor:  # [H, W, 3] x2 -> scalar
    """(1 - w) L1 + w (1 - SSIM), the 3DGS loss (w = 0.2): geometry's `ssim_weight`; refinement passes
    1 - `photo_l1_weight`."""
    return (1 - ssim_weight) * (pred - target).abs().mean() + ssim_weight * ssim_loss(pred, target)


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


def normal_map_loss(rendered: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean of 1 - |cos| between rendered normals [H, W, 3] (blends: any length) and a predicted normal map
    [H, W, 3] (unit; zero where the predictor gave none), over the pixels of `mask` [H, W] that have a prediction.
    Unsigned: a Gaussian's axis has no sign, and a predicted normal's sign is the camera's side."""
    weight = mask * (target.norm(dim=-1) > 0.5)  # [H, W]
    cosine = (F.normalize(rendered, dim=-1, eps=1e-12) * target).sum(-1).abs()
    return ((1.0 - cosine) * weight).sum() / weight.sum().clamp_min(1.0)
