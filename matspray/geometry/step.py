"""One Gaussian Splatting training step: render a view, the loss terms, backward, Adam, density control.

The step keeps the GPU fed: nothing reaches the host between progress reports (the loss and PSNR stay on the
device in `RunningStats`), what a view gives every step (its photo in sRGB, its mask, its pixels' rays) is made once
(`TrainingView`), and the image-sized loss terms are one pure function of tensors (`image_terms`), which on a CUDA
device `ImageTerms` captures in a CUDA graph: one launch forward and one backward instead of a few hundred small
kernels, each of which would otherwise wait on Python.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.data.scene import View
from matspray.device import Graphed, host_to_device
from matspray.errors import NumericalError
from matspray.gaussians import Gaussians
from matspray.geometry.config import GeometryConfig
from matspray.geometry.densify import DensityControl
from matspray.geometry.evaluate import render_view
from matspray.geometry.losses import flatten_loss, normal_consistency_loss, normal_map_loss, photometric_loss
from matspray.geometry.material_edges import view_edge_levels
from matspray.geometry.normals import depth_normals_along
from matspray.geometry.optim import GaussianOptimizer

TERMS = ("photometric", "alpha", "normal", "predicted_normal")  # the image terms, in `image_terms`' order


@dataclass
class TrainingView:
    """A training view with what every step reads of it, made once on its device."""

    view: View
    masked: bool  # the photo's alpha is used (the views of a run all have one)
    srgb: Tensor  # [H, W, 3] the photo, sRGB-encoded
    mask: Tensor  # [H, W] its alpha, or ones where it is not used
    directions: Tensor  # [H, W, 3] world-space ray of each pixel centre, scaled to camera z = 1
    predicted_normals: Tensor  # [H, W, 3] the 2D predictor's normals in world space; zero where it gave none
    material_edges: Tensor | None = None  # [L, H, W] the 2D maps' edge levels (geometry.material_edges), or None

    @staticmethod
    def of(
        view: View, masked: bool, predicted_normals: Tensor | None = None, material_maps: Tensor | None = None
    ) -> "TrainingView":
        """material_maps: the view's 2D maps [h, w, 5] (any size), whose edges densification splits on."""
        mask = view.alpha if masked else torch.ones_like(view.image[..., 0])
        normals = torch.zeros_like(view.image) if predicted_normals is None else predicted_normals.to(view.image)
        if normals.shape != view.image.shape:
            raise ValueError(
                f"view {view.name}: normal map {tuple(normals.shape)} for an image {tuple(view.image.shape)}"
            )
        edges = None if material_maps is None else view_edge_levels(material_maps.to(view.image), mask)
        return TrainingView(
            view, masked, linear_to_srgb(view.image), mask, view.camera.pixel_directions(), normals, edges
        )


def image_terms(
    rgb: Tensor,  # [H, W, 3] rendered sRGB over the background
    alpha: Tensor,  # [H, W] rendered
    normals: Tensor,  # [H, W, 3] blended Gaussian normals (not unit)
    depth: Tensor,  # [H, W] expected camera z
    srgb: Tensor,  # [H, W, 3] the photo
    mask: Tensor,  # [H, W] its alpha (ones without a mask)
    background: Tensor,  # [3] sRGB
    directions: Tensor,  # [H, W, 3] from TrainingView
    center: Tensor,  # [3] the camera's position
    predicted_normals: Tensor,  # [H, W, 3] from TrainingView (zero where there is none)
    ssim_weight: float,
    alpha_weight: float,  # 0: no alpha term
    normal_weight: float,  # 0: no normal term
    predicted_weight: float = 0.0,  # 0: the predicted normals pull nothing
    predicted_depth_weight: float = 0.0,  # 0: ... not the depth's normals
) -> Tensor:  # [5] the weighted photometric, alpha, normal and predicted-normal terms (0 where off), the squared error
    """The image-sized loss terms of a step (train.py's module docstring says what they are). Tensors in, one tensor
    out, no host reads: what a CUDA graph can capture."""
    target = srgb * mask[..., None] + background * (1 - mask[..., None])
    # the prediction is not clamped (the metrics compare clamped values: docs/dev/architecture.md, "Conventions"): a
    # clamp would stop the gradient of pixels that overshoot 1
    photometric = photometric_loss(rgb, target, ssim_weight)
    zero = rgb.new_zeros(())
    alpha_term = alpha_weight * (alpha - mask).abs().mean() if alpha_weight > 0 else zero
    normal_term, predicted_term = zero, zero
    if normal_weight > 0 or predicted_weight > 0 or predicted_depth_weight > 0:
        surface = -F.max_pool2d(-alpha.detach()[None, None], 3, stride=1, padding=1)[0, 0]  # alpha eroded by 1 px
        on_object = surface * (mask > 0.5)
    if normal_weight > 0 or predicted_depth_weight > 0:
        from_depth = depth_normals_along(depth, directions, center)
    if normal_weight > 0:
        normal_term = normal_weight * normal_consistency_loss(normals, from_depth, on_object)
    if predicted_weight > 0:
        predicted_term = predicted_weight * normal_map_loss(normals, predicted_normals, on_object)
    if predicted_depth_weight > 0:
        predicted_term = predicted_term + predicted_depth_weight * normal_map_loss(
            from_depth, predicted_normals, on_object
        )
    squared_error = (rgb.detach().clamp(0, 1) - target.clamp(0, 1)).square().mean()
    return torch.stack([photometric, alpha_term, normal_term, predicted_term, squared_error])


WEIGHTS = ("ssim_weight", "alpha_weight", "normal_weight", "predicted_weight", "predicted_depth_weight")


def weighted_image_terms(weights: tuple[float, ...], *tensors: Tensor) -> Tensor:
    """`image_terms(*tensors)` with the weights in `WEIGHTS`' order: the form `Graphed` captures."""
    return image_terms(*tensors, **dict(zip(WEIGHTS, weights)))


class ImageTerms(Graphed):
    """`image_terms`, captured in CUDA graphs on a CUDA device when `graphs` (one per image size and set of weights,
    made at its first use; matspray.device), called as `terms_of(tensors, weights)`. `capture(function,
    sample_tensors)` replaces `torch.cuda.make_graphed_callables` (and then applies on every device): for tests and
    counts on the CPU."""

    def __init__(self, graphs: bool = True, capture=None):
        super().__init__(weighted_image_terms, "the geometry stage's loss", graphs)
        self.capture = capture or self.capture

    def __call__(self, tensors: tuple[Tensor, ...], weights: tuple[float, ...]) -> Tensor:
        return super().__call__(tuple(weights), *tensors)


def training_losses(
    gaussians: Gaussians,
    target: TrainingView,
    config: GeometryConfig,
    iteration: int,
    generator: torch.Generator,
    image_terms_of: ImageTerms,
):
    """The weighted loss terms of one step {name: scalar}, the render and the render's squared error."""
    view = target.view
    degree = min(config.sh_degree, iteration // config.sh_degree_every)
    masked = target.masked
    background = (
        torch.rand(3, generator=generator, device="cpu")
        if masked and config.random_background
        else torch.zeros(3, device="cpu")
    )
    background = host_to_device(background, gaussians.device)  # drawn on the CPU: the same colours on every device
    render = render_view(gaussians, view.camera, degree, background, absgrad=config.absgrad)
    render.raster.retain_screen_grads()
    normal_on = config.normal_weight > 0 and iteration >= config.normal_from * config.iterations
    # the predicted normals turn the Gaussians' axes from the first step, and the depth's normals once those are
    # smooth enough to compare (the consistency term's start)
    predicted = config.predicted_normal_weight
    weights = (
        config.ssim_weight,
        config.alpha_weight if masked else 0.0,
        config.normal_weight if normal_on else 0.0,
        predicted,
        predicted if normal_on else 0.0,
    )
    rendered = (render.rgb, render.alpha, render.raster.features[..., 3:], render.depth)
    terms = image_terms_of(
        (
            *rendered,
            target.srgb,
            target.mask,
            background,
            target.directions,
            view.camera.center,
            target.predicted_normals,
        ),
        weights,
    )
    losses = {name: terms[i] for i, name in enumerate(TERMS) if i == 0 or weights[i] > 0}
    if config.flatten_weight > 0:
        losses["flatten"] = config.flatten_weight * flatten_loss(gaussians.log_scales)
    return losses, render, terms[4]


def training_step(
    optimizer: GaussianOptimizer,
    density: DensityControl,
    running: "RunningStats",
    target: TrainingView,
    config: GeometryConfig,
    iteration: int,
    generator: torch.Generator,
    image_terms_of: ImageTerms,
    report: bool = False,
) -> str:
    """One optimisation step on `target` with the density schedule after it; returns what densification did ('' if
    nothing). Nothing reaches the host unless `report` (then the running figures are read, and a step since the last
    report that diverged raises) or densification runs."""
    losses, render, squared_error = training_losses(
        optimizer.gaussians(), target, config, iteration, generator, image_terms_of
    )
    total = sum(losses.values())
    running.add(iteration, total.detach(), squared_error)
    if report:
        running.check(losses)
    total.backward()
    density.observe(render.raster, target.view.width, target.view.height, target.material_edges)
    optimizer.step()
    return density.step(iteration, optimizer, generator)


class RunningStats:
    """The loss and a running PSNR of the training steps, kept on the device between host reads, and the first
    step whose loss was not finite."""

    def __init__(self, device: torch.device):
        self.first_bad = torch.full((), -1, dtype=torch.long, device=device)
        self._loss = torch.zeros((), device=device)
        self._psnr: Tensor | None = None
        self.loss, self.psnr = 0.0, 0.0

    def add(self, iteration: int, loss: Tensor, squared_error: Tensor) -> None:
        bad = ~torch.isfinite(loss) & (self.first_bad < 0)
        self.first_bad = torch.where(bad, iteration, self.first_bad)
        self._loss = loss
        step_psnr = (-10.0 * torch.log10(squared_error.detach().clamp_min(1e-10))).clamp(max=99.0)
        self._psnr = step_psnr if self._psnr is None else 0.9 * self._psnr + 0.1 * step_psnr

    def check(self, losses: dict[str, Tensor]) -> None:
        """Read the figures on the host; raises when a step since the start diverged."""
        psnr = self._psnr if self._psnr is not None else torch.zeros_like(self._loss)
        first_bad, self.loss, self.psnr = (
            float(x) for x in torch.stack([self.first_bad.float(), self._loss.float(), psnr.float()]).cpu()
        )
        if first_bad >= 0:
            raise NumericalError(
                f"geometry training diverged at iteration {int(first_bad)} (loss terms now: "
                + ", ".join(f"{k}={float(v):.3g}" for k, v in losses.items())
                + "); try lower learning rates or another seed"
            )
