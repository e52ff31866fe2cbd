"""A last refinement step for metallic: per-Gaussian values fitted through the frozen views to the 2D maps.

Why: the Neural Merger's metallic is a softmax mixture of each Gaussian's lifted per-view medians, so a Gaussian
whose core straddles a metal edge keeps the side that holds most of its core, and the render blends it with its
neighbours: the metal edges come out blurred. On the development objects the pixels near a change of the true
metallic hold most of the 3D metallic's error, even for the truth lifted onto the same Gaussians, and fitting
per-Gaussian values to the true maps through the renderer wins a good part of it back (docs/dev/normals.md, "Metallic",
measured with `benchmarks.metallic_parts`).

What: starting from the merged metallic m0, Adam fits free per-Gaussian values m in [0, 1] to the 2D metallic maps,
one training view per step in a fixed cycle, minimising

    mean over the view's surface pixels of |render(m) / alpha - target|  +  pull * mean over Gaussians of |m - m0|
        +  photo_weight * the view's photometric loss (refinement's, with everything but the metallic as refined)

L1 on the first two: the image term is a per-pixel median, so a view with spurious metallic is outvoted; the pull is
an exact penalty, so a Gaussian moves only where the maps gain more than `pull` per unit of change (the edges),
and keeps the merger's value elsewhere (the interiors, where the merger, helped by the photos, beat the maps). The
photo term keeps the fit from trading relighting for metallic (the merger's base colour was refined together with
its metallic; without the photos the fit relit a little worse); a large weight hands the metallic to the photos,
which then use it to fake shading, as they do normals. Base colour, roughness, normals and light are untouched.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from matspray.errors import SettingError
from matspray.settings import setting

# render(view index, features [N, C]) -> (blended over black [H, W, C], coverage alpha [H, W]): FrozenViews.render
Render = Callable[[int, Tensor], tuple[Tensor, Tensor]]


@dataclass(frozen=True)
class MetallicFitConfig:
    steps: int = setting(0, "Adam steps of the fit, one training view each (0: off, the merger's metallic as it is)")
    pull: float = setting(0.5, "weight of the mean |m - m0| that holds each Gaussian at the merger's value")
    lr: float = setting(0.01, "Adam's rate: about the metallic a value moves per step")
    photo_weight: float = setting(
        5.0,
        "weight of the view's photometric loss (variants with the PBR loss; 0: maps alone)",
    )

    def __post_init__(self):
        if self.steps < 0:
            raise SettingError("steps", f"must be >= 0, got {self.steps}")
        for name in ("pull", "lr", "photo_weight"):
            if not getattr(self, name) >= 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")


def fit_loss(
    values: Tensor,  # [N] metallic being fitted
    start: Tensor,  # [N] the merger's metallic
    blended: Tensor,  # [H, W, 1] values rendered over black
    alpha: Tensor,  # [H, W] coverage
    target: Tensor,  # [H, W] the view's 2D metallic
    surface: Tensor,  # [H, W] weights of the pixels that count (object, well covered)
    pull: float,
) -> Tensor:  # []
    """The fit's objective for one view (see the module's docstring)."""
    rendered = blended[..., 0] / alpha.clamp_min(1e-6)  # the G-buffer's metallic: blended over coverage
    image = ((rendered - target).abs() * surface).sum() / surface.sum().clamp_min(1.0)
    return image + pull * (values - start).abs().mean()


def fit_metallic(
    start: Tensor,  # [N] the merger's metallic, in [0, 1]
    render: Render,
    targets: list[Tensor],  # V maps [H, W]
    surfaces: list[Tensor],  # V weights [H, W]
    config: MetallicFitConfig,
    photo: Callable[[int, Tensor], Tensor] | None = None,
) -> Tensor:  # [N] fitted metallic in [0, 1]
    """Per-Gaussian metallic fitted to the 2D maps through the frozen views (`MetallicFitConfig`); `start` itself when
    the fit is off or there are no views. `photo(view index, metallic [N]) -> []`: the view's photometric loss with
    that metallic (None: the variant has none; the maps alone then)."""
    if config.steps == 0 or not targets:
        return start.detach().clone()
    start = start.detach()
    values = torch.nn.Parameter(start.clone())
    optimizer = torch.optim.Adam([values], lr=config.lr)
    for step in range(config.steps):
        index = step % len(targets)  # a fixed cycle: the same result on every run
        blended, alpha = render(index, values[:, None])
        loss = fit_loss(values, start, blended, alpha, targets[index], surfaces[index], config.pull)
        if photo is not None and config.photo_weight > 0:
            loss = loss + config.photo_weight * photo(index, values)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            values.clamp_(0.0, 1.0)  # projected: metallic is a fraction
    return values.detach()
