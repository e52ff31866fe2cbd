"""Where the 2D material maps change inside a Gaussian's footprint: what densification splits on
(`GeometryConfig.material_edge_threshold`).

The lift gives each Gaussian one value per view (the median over its core), and relighting blends neighbours: a
Gaussian that straddles metal and dielectric, or two base colours, smears the edge. The photometric gradient that
drives 3DGS's densification sees base colour edges in the photos, but a change of roughness or metallic under one
light often shows little there. So each training view's maps give an edge map (the largest change of any channel in
a 3 x 3 window), max-pooled at a few widths; a Gaussian reads the width that matches its footprint at its projected
centre, and densification splits those whose mean over the views that see it reaches the threshold.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.images import linear_to_srgb, resize

# max-pool windows (px) read by Gaussians whose 1-sigma radius is below 1.5 px, below 3 px, and larger
EDGE_WINDOWS = (3, 5, 9)
MIN_SIGMA_PX = 1.0  # a Gaussian narrower than this (1 sigma) blurs no more than a pixel: splitting it gains nothing


def material_edge_map(maps: Tensor, mask: Tensor) -> Tensor:  # [H, W, 5], [H, W] -> [H, W] in [0, 1]
    """The largest change of any channel within each pixel's 3 x 3 window (base colour sRGB-encoded, so that a
    change counts as it shows; roughness and metallic as they are), on the object's interior: the mask eroded by the
    window, since the maps hold nothing outside the object and the silhouette is the photos' to place.
    maps: linear base colour rgb, roughness, metallic."""
    channels = torch.cat([linear_to_srgb(maps[..., :3].clamp(0, 1)), maps[..., 3:].clamp(0, 1)], dim=-1)
    channels = channels.permute(2, 0, 1)[None]  # [1, 5, H, W]
    local_range = F.max_pool2d(channels, 3, stride=1, padding=1) + F.max_pool2d(-channels, 3, stride=1, padding=1)
    inside = (mask > 0.5).to(channels)[None, None]
    interior = -F.max_pool2d(-inside, 3, stride=1, padding=1)  # [1, 1, H, W]
    return (local_range.amax(dim=1, keepdim=True) * interior)[0, 0]


def edge_levels(edges: Tensor) -> Tensor:  # [H, W] -> [L, H, W], L = len(EDGE_WINDOWS)
    """The edge map max-pooled at each of EDGE_WINDOWS: level l holds the strongest edge within its window."""
    return torch.stack([F.max_pool2d(edges[None, None], w, stride=1, padding=w // 2)[0, 0] for w in EDGE_WINDOWS])


def footprint_edges(levels: Tensor, means2d: Tensor, radii: Tensor) -> Tensor:  # [L, H, W], [N, 2], [N] -> [N]
    """Each Gaussian's edge strength: the level that matches its 1-sigma radius (radii: 3-sigma, pixels), read at
    its projected centre (pixels, centres at +0.5); 0 for Gaussians narrower than MIN_SIGMA_PX. No host reads."""
    _, height, width = levels.shape
    sigma = radii.to(levels) / 3.0
    level = (sigma >= 1.5).long() + (sigma >= 3.0).long()
    x = means2d[:, 0].detach().floor().long().clamp(0, width - 1)
    y = means2d[:, 1].detach().floor().long().clamp(0, height - 1)
    return torch.where(sigma >= MIN_SIGMA_PX, levels[level, y, x], torch.zeros_like(sigma))


def view_edge_levels(maps: Tensor, mask: Tensor) -> Tensor:  # [h, w, 5] any size, [H, W] -> [L, H, W]
    """A view's edge levels at its training size: the maps brought to the mask's size (`resize`'s box mode, as the
    normal maps are), then `material_edge_map` and `edge_levels`."""
    maps = resize(maps, *mask.shape, mode="box")
    return edge_levels(material_edge_map(maps.to(mask), mask))
