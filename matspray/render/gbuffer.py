"""G-buffers of views whose geometry is frozen: the blending weights are computed once per view, after
which rendering any per-Gaussian features is a sparse product (and so is its backward pass).

This is what makes material refinement cheap: the Gaussians do not move, only their materials do.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.rasterize import view_weights


class FrozenViews:
    def __init__(self, gaussians: Gaussians, cameras: list[Camera]):
        gaussians = gaussians.detach()
        self.cameras = cameras
        self.means = gaussians.means
        self.weights = [view_weights(gaussians, camera) for camera in cameras]  # (ids [M], pixels [M], w [M]) per view
        self.alphas = [self._blend(index, torch.ones(len(gaussians), 1, device=self.means.device))[..., 0] for index in range(len(cameras))]

    def __len__(self) -> int:
        return len(self.cameras)

    def _blend(self, index: int, features: Tensor) -> Tensor:  # [N, C] -> [H, W, C]
        camera = self.cameras[index]
        gaussian_ids, pixel_ids, weights = self.weights[index]
        hits = features.index_select(0, gaussian_ids) * weights[:, None].to(features.dtype)
        out = features.new_zeros(camera.height * camera.width, features.shape[1]).index_add(0, pixel_ids, hits)
        return out.reshape(camera.height, camera.width, -1)

    def render(self, index: int, features: Tensor) -> tuple[Tensor, Tensor]:
        """features [N, C] -> blended features [H, W, C] over black, and the coverage alpha [H, W]."""
        return self._blend(index, features), self.alphas[index]

    def visible(self, index: int) -> Tensor:  # [N] bool: Gaussians that contribute to the view
        visible = torch.zeros(len(self.means), dtype=torch.bool, device=self.means.device)
        visible[self.weights[index][0]] = True
        return visible

    @functools.cached_property
    def visible_ids(self) -> list[Tensor]:  # per view: ids [K] of the Gaussians that contribute to it
        return [torch.nonzero(self.visible(index)).squeeze(1) for index in range(len(self))]

    def orient_normals(self, index: int, normals: Tensor) -> Tensor:  # [N, 3] -> [N, 3] facing view `index`
        return orient_normals(normals, self.means, self.cameras[index])


def orient_normals(normals: Tensor, means: Tensor, camera: Camera) -> Tensor:  # [N, 3], [N, 3] -> [N, 3]
    """Flip each normal to face the camera (Gaussian normals have no reliable sign)."""
    to_camera = camera.center.to(means) - means
    facing = (normals * to_camera).sum(-1, keepdim=True) >= 0
    return torch.where(facing, normals, -normals)
