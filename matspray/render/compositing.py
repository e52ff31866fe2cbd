"""Front-to-back alpha compositing over flat lists of (ray, Gaussian) hits.

Hits are sorted by ray, then front to back. The transmittance in front of hit k on its ray is
T_k = prod_{j < k on the same ray} (1 - alpha_j), computed as exp of a segmented cumulative sum of
log(1 - alpha) in float64 (a float32 sum over a million hits drifts visibly).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def ray_major_order(
    ray_ids: Tensor,  # [M] long, >= 0
    depth_ranks: Tensor,  # [M] long in [0, num_ranks): front-to-back order along each ray
    num_ranks: int,
) -> Tensor:  # [M] permutation sorting by ray, then by depth rank
    """One radix-friendly sort on the combined integer key ray * num_ranks + rank."""
    key = ray_ids * num_ranks + depth_ranks
    if ray_ids.numel() and int(key.max()) < 2**31 - 1:
        key = key.int()  # sorting int32 is about twice as fast on CPU
    return torch.argsort(key, stable=True)


def ray_major_order_by_depth(ray_ids: Tensor, depths: Tensor) -> Tensor:  # [M] long, [M] float32 > 0 -> [M]
    """Sort by ray, then by a positive float32 depth: the bit patterns of positive IEEE floats order
    like their values, so one integer sort on ray * 2^31 + bits(depth) does it."""
    if depths.dtype != torch.float32:
        raise ValueError(f"ray_major_order_by_depth: depths must be float32, got {depths.dtype}")
    key = ray_ids * (1 << 31) + depths.view(torch.int32).to(torch.int64)
    return torch.argsort(key, stable=True)


def segment_starts(
    ray_ids: Tensor, num_rays: int
) -> Tensor:  # [M] sorted -> [M] index of the first hit of each hit's ray
    # a sum into num_rays counters rather than bincount, which reads the largest id on the host first (on a GPU a wait)
    counts = torch.zeros(num_rays, dtype=torch.long, device=ray_ids.device).index_add_(
        0, ray_ids, torch.ones_like(ray_ids)
    )
    return (torch.cumsum(counts, 0) - counts).index_select(0, ray_ids)


def log_transmittance(
    alphas: Tensor,  # [M] in [0, 1), sorted by ray then front to back
    ray_ids: Tensor,  # [M] long, sorted
    num_rays: int,
) -> tuple[Tensor, Tensor]:
    """log(1 - alpha) [M] and the log transmittance in front of each hit [M], both float64.

    Each term is taken in the dtype of `alphas` (exact enough per hit); the running sum, which spans
    every hit of every ray, is float64.
    """
    log_keep = torch.log1p(-alphas).double()
    before = torch.cumsum(log_keep, 0) - log_keep  # sum over all earlier hits, any ray
    log_T = before - before.index_select(0, segment_starts(ray_ids, num_rays))
    return log_keep, log_T


def surviving_hits(log_keep: Tensor, log_T: Tensor, min_transmittance: float) -> Tensor:  # [M], [M] -> [M] bool
    """Early termination as in 3DGS: a hit is blended only if the transmittance behind it stays
    >= min_transmittance; the first hit that would push it lower, and all after it, are dropped.
    (Transmittance only falls along a ray, so the survivors of each ray are a prefix.)"""
    threshold = math.log(min_transmittance) if min_transmittance > 0 else -math.inf
    return (log_T + log_keep) >= threshold
