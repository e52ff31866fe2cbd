"""Evaluation on the object: compositing with the ground-truth mask, and per-channel scale alignment.

Prediction and ground truth are both composited on the same background with the ground-truth mask,
so the metrics see the object only and the background matches exactly; colour images are then
sRGB-encoded, scalar maps (roughness, metallic) kept as stored; both clamped to [0, 1].

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
