"""G-buffers of views whose geometry is frozen: the blending weights are computed once per view, after
which rendering any per-Gaussian features is a sparse product (and so is its backward pass).

This is what makes material refinement cheap: the Gaussians do not move, only their materials do.
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.rasterize import view_weights


def blend_matrix(column_ids: Tensor, row_ids: Tensor, weights: Tensor, n_rows: int, n_columns: int) -> Tensor:
    """Sparse CSR matrix [n_rows, n_columns] with `weights` [M] at (row_ids, column_ids) [M]: a view's
    blending weights as [pixels, Gaussians] (or, swapped, its transpose)."""
    indices = torch.stack([row_ids.long(), column_ids.long()])
    coo = torch.sparse_coo_tensor(indices, weights, (n_rows, n_columns), check_invariants=False).coalesce()
    with warnings.catch_warnings():  # torch calls sparse CSR "beta"; only its matrix product is used here
        warnings.simplefilter("ignore", UserWarning)
        return coo.to_sparse_csr()


class SparseBlend(torch.autograd.Function):
    """features [N, C] -> matrix @ features [P, C]; the backward pass multiplies by the stored transpose."""

    @staticmethod
    def forward(ctx, features: Tensor, matrix: Tensor, transposed: Tensor) -> Tensor:
        ctx.transposed = transposed
        return matrix @ features

    @staticmethod
    def backward(ctx, grad: Tensor):
        return ctx.transposed @ grad, None, None


class FrozenViews:
    def __init__(self, gaussians: Gaussians, cameras: list[Camera]):
        gaussians = gaussians.detach()
        self.cameras = cameras
        self.means = gaussians.means
        n = len(gaussians)
        self.matrices, self.transposed, self.visible_ids, self.coverage = [], [], [], []
        for camera in cameras:
            gaussian_ids, pixel_ids, weights = view_weights(gaussians, camera)  # [M] each
            pixels = camera.height * camera.width
            self.matrices.append(blend_matrix(gaussian_ids, pixel_ids, weights, pixels, n))  # [HW, N]
            self.transposed.append(blend_matrix(pixel_ids, gaussian_ids, weights, n, pixels))  # [N, HW]
            self.visible_ids.append(torch.unique(gaussian_ids).long())  # [K] Gaussians that contribute to the view
            self.coverage.append(torch.zeros(n, device=weights.device).index_add_(0, gaussian_ids.long(), weights.float()))  # [N] pixels' worth
        self.alphas = [self._blend(index, torch.ones(n, 1, device=self.means.device))[..., 0] for index in range(len(cameras))]

    def __len__(self) -> int:
        return len(self.cameras)

    def _blend(self, index: int, features: Tensor) -> Tensor:  # [N, C] -> [H, W, C]
        camera = self.cameras[index]
        matrix, transposed = self.matrices[index], self.transposed[index]
        if features.dtype != matrix.dtype:  # e.g. float64 for gradcheck
            matrix, transposed = matrix.to(features.dtype), transposed.to(features.dtype)
        return SparseBlend.apply(features.contiguous(), matrix, transposed).reshape(camera.height, camera.width, -1)

    def render(self, index: int, features: Tensor) -> tuple[Tensor, Tensor]:
        """features [N, C] -> blended features [H, W, C] over black, and the coverage alpha [H, W]."""
        return self._blend(index, features), self.alphas[index]

    def visible(self, index: int) -> Tensor:  # [N] bool: Gaussians that contribute to the view
        visible = torch.zeros(len(self.means), dtype=torch.bool, device=self.means.device)
        visible[self.visible_ids[index]] = True
        return visible

    def contributing_ids(self, index: int, min_coverage: float) -> Tensor:  # [K'] subset of visible_ids
        """The visible Gaussians whose blending weights in view `index` add up to >= `min_coverage` pixels."""
        visible = self.visible_ids[index]
        return visible[self.coverage[index][visible] >= min_coverage] if min_coverage > 0 else visible

    def orient_normals(self, index: int, normals: Tensor) -> Tensor:  # [N, 3] -> [N, 3] facing view `index`
        return orient_normals(normals, self.means, self.cameras[index])


def orient_normals(normals: Tensor, means: Tensor, camera: Camera) -> Tensor:  # [N, 3], [N, 3] -> [N, 3]
    """Flip each normal to face the camera (Gaussian normals have no reliable sign)."""
    to_camera = camera.center.to(means) - means
    facing = (normals * to_camera).sum(-1, keepdim=True) >= 0
    return torch.where(facing, normals, -normals)
