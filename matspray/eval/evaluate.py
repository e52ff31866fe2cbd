"""PSNR, SSIM and LPIPS of one predicted image against its ground truth, on the object.

Two regions (`matspray.eval.masked` describes them): the ground-truth-mask figure (`pred_alpha`
None, the historical one) and the silhouette-counting union figure (`pred_alpha` given).
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping, Sequence

import torch

from matspray.errors import DataError
from matspray.eval.lpips import MIN_SIZE as LPIPS_MIN_SIZE
from matspray.eval.lpips import PerceptualMetric
from matspray.eval.masked import composite_on_background, covered_box, union_weights
from matspray.metrics import as_image, mse, psnr, psnr_from_mse, ssim

METRICS = ("psnr", "ssim", "lpips")


def evaluate_images(
    pred, target, mask, lpips: PerceptualMetric | None = None, background=1.0, encoding: str = "srgb", pred_alpha=None
) -> dict[str, float | None]:
    """Metrics of linear `pred` vs `target` [H, W, C] (or [H, W] maps) on `background`, encoded as
    `encoding` ("srgb" for colour, "raw" for roughness/metallic). LPIPS sees single-channel maps
    repeated to RGB; it is None when `lpips` is None (unavailable), never a made-up number.

    pred_alpha None: the object-mask (GT) figure. Both are composited with the ground-truth `mask`
        [H, W] and scored over the full image (errors off the true object cannot show).
    pred_alpha [H, W]: the object + silhouette (union) figure. `pred` is composited with its own
        alpha, `target` with `mask`; PSNR is the mean over the union weights max(pred_alpha, mask),
        SSIM the window mean weighted by them (`metrics.ssim`), LPIPS the network's spatial mean over
        the union's bounding box (grown to the network's minimum size): LPIPS takes no weights, and the
        box keeps it about the object and its silhouette rather than the empty frame, like the other two.
    """
    pred = as_image(pred, "pred")  # [H, W, C] float64
    target = as_image(target, "target").to(pred.device)
    region, rows, columns = None, slice(None), slice(None)
    if pred_alpha is None:
        pred_on_object = composite_on_background(pred, mask, background, encoding)  # [H, W, C] in [0, 1]
    else:
        alpha = _as_alpha(pred_alpha, pred)  # [H, W]
        pred_on_object = composite_on_background(pred, alpha, background, encoding)
        region = union_weights(alpha, torch.as_tensor(mask).to(alpha))  # [H, W]
        rows, columns = covered_box(region, LPIPS_MIN_SIZE)
    target_on_object = composite_on_background(target, mask, background, encoding)
    result: dict[str, float | None] = {
        "psnr": psnr(pred_on_object, target_on_object, region),
        "ssim": ssim(pred_on_object, target_on_object, region),
        "lpips": None,
    }
    if lpips is not None:
        result["lpips"] = lpips.distance(
            _as_rgb(pred_on_object[rows, columns]), _as_rgb(target_on_object[rows, columns])
        )
    return result


def _as_alpha(pred_alpha, pred) -> torch.Tensor:  # [H, W] (| [H, W, 1]) -> [H, W] float64 in [0, 1]
    alpha = torch.as_tensor(pred_alpha).to(device=pred.device, dtype=torch.float64)
    if alpha.dim() == 3 and alpha.shape[-1] == 1:
        alpha = alpha[..., 0]
    if not torch.isfinite(alpha).all():
        raise DataError("pred_alpha: contains NaN or Inf values")
    return alpha.clamp(0.0, 1.0)  # a render's coverage may overshoot [0, 1] by rounding


def _as_rgb(image):  # [H, W, 1 | 3] -> [H, W, 3]
    return image.expand(-1, -1, 3) if image.shape[-1] == 1 else image


def pooled_union_psnr(
    preds: Sequence, pred_alphas: Sequence, targets: Sequence, masks: Sequence, background=0.0
) -> float:
    """PSNR (dB) of the squared error pooled over views, silhouette-counting: each prediction [H, W]
    composited with its own alpha, each truth with its mask, on `background` (raw values), weighted
    by the union of each view's silhouettes. The union counterpart of `metallic.object_metallic_psnr`
    (pooled, black background), so the metallic infinity rule applies to it alike; inf when exact."""
    pred_maps, target_maps, weights = [], [], []
    for pred, alpha, target, mask in zip(preds, pred_alphas, targets, masks, strict=True):
        pred = as_image(pred, "pred")  # [H, W, 1]
        alpha = _as_alpha(alpha, pred)
        pred_maps.append(composite_on_background(pred, alpha, background, "raw"))
        target_maps.append(composite_on_background(as_image(target, "target").to(pred.device), mask, background, "raw"))
        weights.append(union_weights(alpha, torch.as_tensor(mask).to(alpha)))
    # views stacked along the height: a weighted mean over [V*H, W] is the mean pooled over the views
    return psnr_from_mse(mse(torch.cat(pred_maps), torch.cat(target_maps), torch.cat(weights)))


def average_metrics(records: Iterable[Mapping[str, float | None]]) -> dict[str, float | None]:
    """Mean of each metric over views (or objects). A metric that is None in any record (LPIPS
    unavailable) stays None; an infinite PSNR makes the mean infinite."""
    records = list(records)
    if not records:
        return {}
    averaged: dict[str, float | None] = {}
    for key in records[0]:
        values = [record.get(key) for record in records]
        averaged[key] = None if any(v is None for v in values) else math.fsum(values) / len(values)
    return averaged
