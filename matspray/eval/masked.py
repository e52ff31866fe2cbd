"""Evaluation on the object: compositing, the two scored regions, and per-channel scale alignment.

Two figures are reported for every image (`matspray.eval.evaluate.evaluate_images`):
  object mask (GT)   prediction and ground truth both composited on the same background with the
                     ground-truth mask, scored over the full image. The background matches exactly by
                     construction, so whatever the prediction shows at or outside the true silhouette
                     is hidden: a mesh that bulges or misses a part is not penalised for it.
  object + silhouette (union)
                     each image composited with its OWN coverage (the prediction with its rendered
                     alpha, the truth with the true mask) on the same background, scored over the union
                     of the two: weights max(pred_alpha, true_mask) (`union_weights`). Extra and missing
                     silhouette pixels then differ from the truth and count.
Colour images are then sRGB-encoded, scalar maps (roughness, metallic) kept as stored; both clamped to [0, 1].

Scale alignment (optional, reported separately) follows the NeRFactor / TensoIR evaluations: the
prediction is multiplied per channel by the median of ground truth / prediction over object pixels,
in linear space, before compositing. It removes the global albedo-vs-light scale ambiguity.
"""

from __future__ import annotations

import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.errors import ConfigError, DataError

ENCODINGS = ("srgb", "raw")
RATIO_FLOOR = 1e-6  # predictions below this count as this when forming GT / prediction


def composite_on_background(image, mask, background=1.0, encoding: str = "srgb") -> Tensor:
    """Composite linear `image` [..., H, W, C] over `background` with `mask` [..., H, W] in [0, 1].

    background: a float or C floats, linear. encoding: "srgb" (colour images: the result is
    sRGB-encoded) or "raw" (scalar maps: kept as they are). Returns [..., H, W, C] in [0, 1].
    """
    if encoding not in ENCODINGS:
        raise ConfigError(f"encoding must be one of {ENCODINGS}, got '{encoding}'")
    image = torch.as_tensor(image)
    if not torch.is_floating_point(image):
        raise DataError(f"image: expected floating-point values, got {image.dtype}")
    if image.dim() < 3:
        raise DataError(f"image: expected [H, W, C] (or a stack [..., H, W, C]), got shape {list(image.shape)}")
    if not torch.isfinite(image).all():
        raise DataError("image: contains NaN or Inf values")
    weights = torch.as_tensor(mask).to(image)
    if tuple(weights.shape) != tuple(image.shape[:-1]):
        raise DataError(f"mask: shape {list(weights.shape)} does not match the image's {list(image.shape[:-1])}")
    if not torch.isfinite(weights).all() or float(weights.min()) < 0.0 or float(weights.max()) > 1.0:
        raise DataError("mask: values must be finite and in [0, 1]")
    fill = torch.as_tensor(background, dtype=image.dtype, device=image.device).flatten()
    if fill.numel() not in (1, image.shape[-1]) or not torch.isfinite(fill).all() or float(fill.min()) < 0.0:
        raise ConfigError(f"background: expected one or {image.shape[-1]} finite values >= 0, got {background!r}")
    weights = weights[..., None]  # [..., H, W, 1]
    composite = image * weights + fill * (1.0 - weights)
    return linear_to_srgb(composite) if encoding == "srgb" else composite.clamp(0.0, 1.0)


def union_weights(pred_alpha, mask) -> Tensor:  # [..., H, W], [..., H, W] -> [..., H, W] float64 in [0, 1]
    """Per-pixel weights of the silhouette-counting region: max(pred_alpha, mask).

    Soft rather than a hard union at 0.5 because the composites are themselves soft blends by the same
    coverages: a pixel's error already scales with how much either image covers it, so weighting it by
    that coverage keeps the figure continuous in alpha (no threshold that a faint halo or a floater just
    under 0.5 slips under, no flicker at the edge). For binary masks it is exactly the hard union.
    """
    alpha = torch.as_tensor(pred_alpha).to(torch.float64)
    truth = torch.as_tensor(mask).to(alpha)
    if alpha.shape != truth.shape:
        raise DataError(f"pred_alpha {list(alpha.shape)} and mask {list(truth.shape)} differ in shape")
    return torch.maximum(alpha, truth)


def covered_box(weights, min_size: int = 1) -> tuple[slice, slice]:
    """Rows and columns of the smallest box holding every pixel of `weights` [H, W] above zero, grown
    about its centre to at least `min_size` per side (kept inside the image; the whole side when the
    image is smaller). A spatial metric that cannot take weights (LPIPS) is scored on this box."""
    covered = torch.as_tensor(weights) > 0  # [H, W]
    if not covered.any():
        raise DataError("mask: selects no pixels; the union of the silhouettes is empty")
    spans = []
    for axis in (1, 0):  # rows: any along width; columns: any along height
        indices = torch.nonzero(covered.any(dim=axis)).flatten()
        first, last, length = int(indices[0]), int(indices[-1]) + 1, covered.shape[1 - axis]
        size = max(last - first, min(min_size, length))
        first = min(max(0, first - (size - (last - first)) // 2), length - size)  # centred, then pushed inside
        spans.append(slice(first, first + size))
    return spans[0], spans[1]


def _object_pixels(values: Tensor, mask, name: str) -> Tensor:  # [..., H, W, C], [..., H, W] -> [P, C]
    selected = torch.as_tensor(mask).to(values.device)
    if tuple(selected.shape) != tuple(values.shape[:-1]):
        raise DataError(f"mask: shape {list(selected.shape)} does not match {name}'s {list(values.shape[:-1])}")
    selected = selected > 0.5 if torch.is_floating_point(selected) else selected.bool()
    if not selected.any():
        raise DataError("mask: selects no object pixels; cannot align the scale")
    return values[selected]


def channel_scale(pred, target, mask) -> Tensor:
    """Per-channel factor [C]: median over object pixels (mask > 0.5) of target / prediction.

    pred, target: linear [..., H, W, C] (a stack of views pools all of them, as TensoIR's global
    ratio); mask [..., H, W]. The median is torch's lower median; predictions are floored at 1e-6.
    """
    pred, target = torch.as_tensor(pred), torch.as_tensor(target)
    if pred.shape != target.shape:
        raise DataError(f"pred {list(pred.shape)} and target {list(target.shape)} differ in shape")
    predicted = _object_pixels(pred.to(torch.float64), mask, "pred")  # [P, C]
    wanted = _object_pixels(target.to(predicted), mask, "target")  # [P, C]
    if not (torch.isfinite(predicted).all() and torch.isfinite(wanted).all()):
        raise DataError("pred/target: contain NaN or Inf on the object")
    return (wanted / predicted.clamp_min(RATIO_FLOOR)).median(dim=0).values  # [C]


def align_scale(pred, target, mask) -> Tensor:
    """`pred` [..., H, W, C] times the per-channel median ratio of `channel_scale` (same dtype)."""
    pred = torch.as_tensor(pred)
    return pred * channel_scale(pred, target, mask).to(pred)
