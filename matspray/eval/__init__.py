"""Evaluation: PSNR, SSIM, LPIPS on the object, the metallic infinity rule, and the paper's tables."""

from matspray.eval.evaluate import average_metrics, evaluate_images
from matspray.eval.lpips import LPIPS, load_lpips
from matspray.eval.masked import align_scale, channel_scale, composite_on_background
from matspray.eval.metallic import MetallicPsnr, metallic_psnr_over_objects, object_metallic_psnr
from matspray.eval.tables import (
    ablation_table,
    material_table,
    softmax_table,
    tables_markdown,
    timings_table,
    write_tables,
)
from matspray.metrics import psnr, ssim

__all__ = [
    "LPIPS",
    "MetallicPsnr",
    "ablation_table",
    "align_scale",
    "average_metrics",
    "channel_scale",
    "composite_on_background",
    "evaluate_images",
    "load_lpips",
    "material_table",
    "metallic_psnr_over_objects",
    "object_metallic_psnr",
    "psnr",
    "softmax_table",
    "ssim",
    "tables_markdown",
    "timings_table",
    "write_tables",
]
