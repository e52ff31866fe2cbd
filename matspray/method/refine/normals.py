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

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
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


def nearest_neighbours(points: Tensor, k: int) -> tuple[Tensor, Tensor]:  # [P, 3] -> [P, k], [P, k]
    """The squared distances to the k nearest other points, ascending, and their indices (k at most P - 1), found by
    scipy's k-d tree: comparing every pair, as `geometry.init.neighbour_spacing` does for a few thousand points, takes
    seconds for the tens of thousands of a trained object."""
    k = min(k, len(points) - 1)
    if k < 1:
        return points.new_zeros(len(points), 0), torch.zeros(len(points), 0, dtype=torch.long, device=points.device)
    array = points.detach().cpu().double().numpy()
    distances, indices = cKDTree(array).query(array, k + 1)  # [P, k + 1]: each point itself among them, usually first
    own = indices == np.arange(len(array))[:, None]
    order = np.argsort(own, axis=1, kind="stable")[:, :k]  # itself (or, among duplicates, the farthest) left out
    distances, indices = (np.take_along_axis(values, order, axis=1) for values in (distances, indices))
    return torch.from_numpy(distances**2).to(points), torch.from_numpy(indices).to(points.device)


def smoothed_normals(
    normals: Tensor, means: Tensor, weights: Tensor, neighbours: int = 16, agreement: float = 4.0
) -> Tensor:  # [N, 3] unit, [N, 3], [N] -> [N, 3] unit
    """Each normal averaged with its `neighbours` nearest Gaussians' (by centre), each weighted by `weights` (e.g.
    opacity), by a Gaussian of its distance at the point's own neighbour spacing, and by |cos|^`agreement` with the
    normal (so a crease keeps its two sides). Normals have no sign: each neighbour is flipped to agree first. The
    normal a Gaussian's shortest axis gives is noisy where it straddles a curve or was trained on few views; its
    neighbours on the same surface see other views."""
    d2, index = nearest_neighbours(means, neighbours)  # [N, K], [N, K]
    scale = d2.mean(dim=1, keepdim=True).clamp_min(1e-12)  # [N, 1]
    others = normals[index]  # [N, K, 3]
    cos = (others * normals[:, None]).sum(-1)  # [N, K]
    w = weights[index] * torch.exp(-d2 / scale) * cos.abs().pow(agreement)  # [N, K]
    total = normals * weights[:, None] + ((w * cos.sign())[..., None] * others).sum(1)
    return F.normalize(total, dim=-1, eps=1e-12)
