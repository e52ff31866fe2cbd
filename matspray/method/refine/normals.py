"""Per-Gaussian shading normals refined by the rendering loss (paper section 3: "the materials maps and normals
are further refined based on a rendering loss").

Each Gaussian's normal is a free 3-vector that starts at the geometry stage's normal and is normalised before
shading, so the photometric loss can turn it where the geometry's shortest axis is off (lumpy surfaces, Gaussians
straddling an edge), while `normal_prior` keeps it near the geometry's normal and `geometry.losses.normal_map_loss`
can pull the rendered normals towards a 2D model's predicted normal map. Geometry (positions, shapes, opacities)
stays frozen: only the direction that shading reads changes, so each view's blending weights are still computed
once.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ShadingNormals(nn.Module):
    """Learnable unit normals [N, 3], initialised at `initial` [N, 3] (unit; any orientation: each view flips them
    to face it)."""

    def __init__(self, initial: Tensor):
        super().__init__()
        # the raw vector, not an angle pair: no pole, and Adam's step turns it by about lr radians at unit length
        self.direction = nn.Parameter(F.normalize(initial.detach(), dim=-1).clone())

    def forward(self) -> Tensor:  # -> [N, 3] unit
        return F.normalize(self.direction, dim=-1, eps=1e-12)


def normal_prior(normals: Tensor, targets: Tensor) -> Tensor:  # [K, 3] unit, [K, 3] unit -> []
    """Mean of 1 - |cos| between each normal and its target: 0 when aligned either way (Gaussian normals have no
    sign, and a predicted normal's sign is the camera's side), 1 at right angles."""
    if len(normals) == 0:
        return normals.sum() * 0.0  # keeps the graph (and the device) for an empty view
    return (1.0 - (normals * targets).sum(-1).abs()).mean()


def angle_change_degrees(before: Tensor, after: Tensor) -> Tensor:  # [N, 3], [N, 3] -> [N] in [0, 90]
    """Unsigned angle between two sets of unoriented normals, in degrees: how far refinement turned each one."""
    cos = (F.normalize(before, dim=-1) * F.normalize(after, dim=-1)).sum(-1).abs().clamp(max=1.0)
    return torch.rad2deg(torch.acos(cos))
