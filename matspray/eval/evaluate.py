"""PSNR, SSIM and LPIPS of one predicted image against its ground truth, on the object."""

from __future__ import annotations

import math
from typing import Iterable, Mapping

from matspray.eval.lpips import PerceptualMetric
from matspray.eval.masked import composite_on_background
from matspray.eval.metrics import as_image, psnr, ssim

METRICS = ("psnr", "ssim", "lpips")


def evaluate_images(pred, target, mask, lpips: PerceptualMetric | None = None, background=1.0,
                    encoding: str = "srgb") -> dict[str, float | None]:
    """Metrics of linear `pred` vs `target` [H, W, C] (or [H, W] maps), both composited on
    `background` with the ground-truth `mask` [H, W] and encoded as `encoding` ("srgb" for colour,
    "raw" for roughness/metallic). LPIPS sees single-channel maps repeated to RGB; it is None when
    `lpips` is None (unavailable), never a made-up number.
    """
    pred = as_image(pred, "pred")  # [H, W, C] float64
    target = as_image(target, "target").to(pred.device)
    pred_on_object = composite_on_background(pred, mask, background, encoding)  # [H, W, C] in [0, 1]
    target_on_object = composite_on_background(target, mask, background, encoding)
    result: dict[str, float | None] = {
        "psnr": psnr(pred_on_object, target_on_object),
        "ssim": ssim(pred_on_object, target_on_object),
        "lpips": None,
    }
    if lpips is not None:
        result["lpips"] = lpips.distance(_as_rgb(pred_on_object), _as_rgb(target_on_object))
    return result


def _as_rgb(image):  # [H, W, 1 | 3] -> [H, W, 3]
    return image.expand(-1, -1, 3) if image.shape[-1] == 1 else image


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
