"""3D Gaussians: the scene representation every stage shares.

Parameters are stored raw (as optimised); the properties give the activated values:
scales = exp(log_scales), opacities = sigmoid(opacity_logits), rotations = normalised quaternions
(w, x, y, z). Colour is spherical harmonics: sh [N, (degree + 1)^2, 3], coefficient 0 is the DC term.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass
class Gaussians:
    means: Tensor  # [N, 3]
    log_scales: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] (w, x, y, z), not necessarily unit length
    opacity_logits: Tensor  # [N]
    sh: Tensor  # [N, K, 3] spherical-harmonics colour coefficients, K = (degree + 1)^2

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> Tensor:  # [N, 3]
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:  # [N]
        return torch.sigmoid(self.opacity_logits)

    @property
    def rotations(self) -> Tensor:  # [N, 4] unit quaternions (w, x, y, z)
        return F.normalize(self.quats, dim=-1)

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    def rotation_matrices(self) -> Tensor:  # [N, 3, 3], columns are the Gaussian's local axes in world space
        return quaternion_to_matrix(self.rotations)

    def scaled_axes(self) -> Tensor:  # [N, 3, 3] L = R diag(scales): columns are the scaled local axes
        return self.rotation_matrices() * self.scales[:, None, :]

    def covariances(self) -> Tensor:  # [N, 3, 3] world-space covariance R S S^T R^T = L L^T
        L = self.scaled_axes()
        return L @ L.transpose(1, 2)

    def normals(self) -> Tensor:  # [N, 3] unit axis of the smallest scale (unoriented)
        # R e = (1 - 2 |v|^2) e + 2 (v . e) v + 2 w (v x e), the entries of `quaternion_to_matrix` (w, v): the one
        # column of the rotation matrix that is wanted, in a third of the operations of the whole matrix (training
        # takes it every step)
        q = self.rotations
        w, v = q[:, :1], q[:, 1:]
        axes = torch.arange(3, device=q.device)  # (not one_hot, which reads its input's range on the host)
        e = (self.log_scales.argmin(dim=-1, keepdim=True) == axes).to(q)  # [N, 3] the shortest local axis
        return (
            (1 - 2 * (v * v).sum(-1, keepdim=True)) * e
            + 2 * (v * e).sum(-1, keepdim=True) * v
            + 2 * w * (torch.linalg.cross(v, e, dim=-1))
        )

    def subset(self, keep: Tensor) -> "Gaussians":
        """The Gaussians selected by a boolean mask or index tensor."""
        return Gaussians(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def detach(self) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def to(self, device=None, dtype=None) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name).to(device=device, dtype=dtype) for f in fields(self)})


def quaternion_to_matrix(q: Tensor) -> Tensor:  # [N, 4] unit (w, x, y, z) -> [N, 3, 3]
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))
