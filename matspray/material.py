"""The per-Gaussian material layout, in one place.

Materials are 5 channels on the last axis, [..., 5]: base colour RGB (linear), roughness (perceptual),
metallic. Lifted per-view values are [N, V, 5], assets [N, 5], 2D maps [H, W, 5]. The channel names
are also the asset PLY's property names.
"""

from __future__ import annotations

import torch
from torch import Tensor

CHANNELS = ("base_color_r", "base_color_g", "base_color_b", "roughness", "metallic")
N_CHANNELS = len(CHANNELS)
BASE_COLOR = slice(0, 3)
ROUGHNESS_INDEX = 3
METALLIC_INDEX = 4
# the channel groups the Neural Merger fuses separately (one MLP each)
GROUPS = {
    "base_color": BASE_COLOR,
    "roughness": slice(ROUGHNESS_INDEX, ROUGHNESS_INDEX + 1),
    "metallic": slice(METALLIC_INDEX, METALLIC_INDEX + 1),
}


def stack(base_color: Tensor, roughness: Tensor, metallic: Tensor) -> Tensor:  # [..., 3], [...], [...] -> [..., 5]
    return torch.cat([base_color, roughness[..., None], metallic[..., None]], dim=-1)


def unstack(
    materials: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:  # [..., 5] -> base colour [..., 3], roughness [...], metallic [...]
    return materials[..., BASE_COLOR], materials[..., ROUGHNESS_INDEX], materials[..., METALLIC_INDEX]


def zeros(*shape: int, device=None, dtype=torch.float32) -> Tensor:  # -> [*shape, 5]
    return torch.zeros(*shape, N_CHANNELS, device=device, dtype=dtype)
