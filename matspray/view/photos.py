"""The training photo nearest to the viewer's camera, shown beside the render to compare with what was captured."""

from __future__ import annotations

import numpy as np
import torch

from matspray.data.images import linear_to_srgb


def nearest_view(centers, target, position) -> int:
    """Index of the camera among `centers` [V, 3] whose direction from `target` [3] is closest in angle to that of
    `position` [3] (ties: the one nearest in distance). Angles, not distances, because the viewer zooms freely."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    target, position = np.asarray(target, dtype=np.float64), np.asarray(position, dtype=np.float64)
    offsets = centers - target
    here = position - target
    unit = offsets / np.maximum(np.linalg.norm(offsets, axis=-1, keepdims=True), 1e-12)
    cosines = unit @ (here / max(np.linalg.norm(here), 1e-12))
    distance = np.abs(np.linalg.norm(offsets, axis=-1) - np.linalg.norm(here))
    return int(np.lexsort((distance, -np.round(cosines, 9)))[0])


def photo_image(view, backdrop: float) -> np.ndarray:  # -> [H, W, 3] uint8 sRGB
    """A training view as the page shows it: the photo over the viewer's backdrop grey where its mask is empty."""
    rgb = view.image
    if view.alpha is not None:
        rgb = rgb * view.alpha[..., None] + backdrop * (1 - view.alpha[..., None])
    return (linear_to_srgb(rgb.float()).clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
