"""Metallic PSNR over objects with the paper's infinity rule (Table 1, footnote *).

A non-metallic object (ground truth zero on the whole object) whose prediction is zero on the whole
object has zero error, so an infinite PSNR. Such objects are left out of the average, and their
count is reported next to it ("inf*/27.202" in the paper). Every other object contributes a finite
PSNR. (Any object predicted exactly has zero error and counts as infinite too; for a metallic one
that does not happen with real predictions.)

An object's metallic PSNR is computed from the squared error pooled over all its test views
(prediction and ground truth composited on a black background with the ground-truth mask), not
from a mean of per-view PSNRs: a single view where a partly metallic object shows no metal and is
predicted exactly would otherwise make the whole object infinite.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import torch
from torch import Tensor

from matspray.errors import DataError
from matspray.eval.masked import composite_on_background
from matspray.metrics import psnr_from_mse


class MetallicPsnr(NamedTuple):
    mean: float | None  # mean PSNR over the objects with a finite PSNR; None if there are none
    infinite: int  # objects with infinite PSNR (non-metallic, predicted all zero), left out of `mean`
    per_object: list[float]  # each object's PSNR, math.inf for the infinite ones


def _as_views(values, name: str) -> Tensor:  # [H, W] | [V, H, W] (| trailing 1) -> [V, H, W, 1] float64
    values = torch.as_tensor(values).to(torch.float64)
    if values.dim() >= 3 and values.shape[-1] == 1:
        values = values[..., 0]
    if values.dim() == 2:
        values = values[None]
    if values.dim() != 3:
        raise DataError(f"{name}: expected a metallic map [H, W] or views [V, H, W], got shape {list(values.shape)}")
    return values[..., None]


def object_metallic_psnr(pred, target, mask) -> float:
    """PSNR (dB) of one object's metallic maps, pooled over its views; inf when the error is zero.

    pred, target: [V, H, W] (or [H, W]) metallic values in [0, 1]; mask: ground-truth alpha, same shape.
    """
    pred, target = _as_views(pred, "pred"), _as_views(target, "target")
    weights = _as_views(mask, "mask")[..., 0]
    if pred.shape != target.shape or weights.shape != pred.shape[:-1]:
        raise DataError(
            f"pred {list(pred.shape[:-1])}, target {list(target.shape[:-1])} and mask "
            f"{list(weights.shape)} must have the same shape"
        )
    for name, values in (("pred", pred), ("target", target)):
        if not torch.isfinite(values).all() or float(values.min()) < 0.0 or float(values.max()) > 1.0:
            raise DataError(f"{name}: metallic values must be finite and in [0, 1]")
    on_object_pred = composite_on_background(pred, weights, background=0.0, encoding="raw")
    on_object_target = composite_on_background(target, weights, background=0.0, encoding="raw")
    return psnr_from_mse(float(((on_object_pred - on_object_target) ** 2).mean()))


def metallic_psnr_over_objects(objects: Sequence[tuple]) -> MetallicPsnr:
    """The paper's metallic PSNR over objects: each item is (pred, target, mask) of one object."""
    if len(objects) == 0:
        raise DataError("metallic PSNR: no objects given")
    per_object = [object_metallic_psnr(pred, target, mask) for pred, target, mask in objects]
    finite = [value for value in per_object if math.isfinite(value)]
    mean = sum(finite) / len(finite) if finite else None
    return MetallicPsnr(mean=mean, infinite=len(per_object) - len(finite), per_object=per_object)
