"""What `rasterize` returns, whichever backend drew it (matspray.render.raster.rasterize)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class RasterOutput:
    features: Tensor  # [H, W, C] blended features plus (1 - alpha) * background
    alpha: Tensor  # [H, W] accumulated opacity sum_k w_k = 1 - prod_k (1 - alpha_k)
    depth: Tensor  # [H, W] accumulated camera z, sum_k w_k z_k (NOT divided by alpha; see expected_depth)
    means2d: Tensor  # [N, 2] projected centres in pixels, 0 where gsplat did not draw (gradients:
    # retain_screen_grads / screen_grads)
    radii: Tensor  # [N] 3-sigma pixel radius of the major axis of each drawn Gaussian, 0 if not drawn (every backend)
    backend: str  # "torch", "numba" or "gsplat": the rasterizer that drew this
    # the tensor through which d loss / d means2d flows: [N, 2] (torch) or gsplat's [1, N, 2]; a view of it taken
    # after rendering is outside the graph, so the gradients are read from this one
    screen: Tensor
    pixel_hits: int | None = None  # blended (Gaussian, pixel) pairs (backends torch and numba)
    tile_hits: int | None = None  # (Gaussian, 16x16 tile) pairs (backend gsplat)

    @property
    def expected_depth(self) -> Tensor:  # [H, W] depth / alpha (the surface depth), 0 where alpha is 0
        return torch.where(self.alpha > 0, self.depth / self.alpha.clamp_min(1e-12), torch.zeros_like(self.depth))

    @property
    def visible(self) -> Tensor:  # [N] bool: the Gaussian was drawn in this view
        return self.radii > 0

    def retain_screen_grads(self) -> None:
        """Call before backward to read `screen_grads` (and `screen_absgrads`) after it."""
        if self.screen.requires_grad:
            self.screen.retain_grad()

    @property
    def screen_grads(self) -> Tensor | None:  # [N, 2] d loss / d means2d (pixels), None before backward
        if not (self.screen.is_leaf or self.screen.retains_grad):  # no grad to read (and torch warns if we look)
            return None
        grad = self.screen.grad
        return None if grad is None else grad.reshape(-1, 2)

    @property
    def screen_absgrads(self) -> Tensor | None:  # [N, 2] sum over pixels of |d loss_pixel / d means2d|, None unless
        # rendered with rasterize(..., absgrad=True) and after backward. gsplat sets it at each backward, torch adds to
        # it at each (as .grad): the same after the one backward per render that densification does
        absgrad = getattr(self.screen, "absgrad", None)
        return None if absgrad is None else absgrad.reshape(-1, 2)
