"""How good and how view-consistent are 2D material predictions? The figures later stages must improve on.

On a `matspray synth` object (true maps and depth next to every view), for the ground-truth maps
(the sanity floor) and the simulated predictor at the given severity:
- PSNR against ground truth over object pixels (alpha > 0.5), per view then averaged: base color on
  sRGB-encoded values (as stored and as images are compared), roughness and metallic linear. A view
  whose error is exactly 0 has infinite PSNR; such views are counted and left out of the mean
  (the paper's rule for metallic).
- multi-view inconsistency: surface points of every view are reprojected with the true depth into
  every other view where they are visible, and the standard deviation of the values the views give
  the same point is averaged (matspray.predictors.consistency; base color: mean over RGB, sRGB-encoded).

    python -m benchmarks.predictors --data DIR [--split train] [--severity 1] [--seed 0] [--batch-size 8]
(from the repository root; `python benchmarks/predictors.py` works where matspray is installed)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

from matspray.data import linear_to_srgb, load_scene
from matspray.errors import MatsprayError
from matspray.predictors import CHANNELS, PredictorOptions, make_predictor, predict_views
from matspray.predictors.consistency import multiview_spread
from matspray.predictors.ground_truth import check_ground_truth, read_ground_truth, read_ground_truth_depth


def channel_values(maps) -> dict[str, torch.Tensor]:  # name -> [H, W, C] in the space metrics use
    return {
        "basecolor": linear_to_srgb(maps.basecolor),
        "roughness": maps.roughness[..., None],
        "metallic": maps.metallic[..., None],
    }


def psnr(prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> float:
    """prediction, truth [H, W, C] in [0, 1], mask [H, W] bool -> PSNR in dB (inf when equal)."""
    mse = float(((prediction - truth) ** 2)[mask].mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def mean_psnr(values: list[float]) -> tuple[float, int]:
    finite = [v for v in values if math.isfinite(v)]
    return (sum(finite) / len(finite) if finite else math.inf), len(values) - len(finite)


def evaluate(views, predicted, truths, depths) -> dict:
    figures = {}
    for channel in CHANNELS:
        scores = []
        for view in views:
            mask = view.alpha > 0.5 if view.alpha is not None else depths[view.name] > 0
            scores.append(
                psnr(channel_values(predicted[view.name])[channel], channel_values(truths[view.name])[channel], mask)
            )
        figures[f"psnr_{channel}"], figures[f"infinite_{channel}"] = mean_psnr(scores)
    stacked = [torch.cat(list(channel_values(predicted[v.name]).values()), dim=-1) for v in views]  # [H, W, 5]
    spread = multiview_spread([v.camera for v in views], [depths[v.name] for v in views], stacked)
    figures["spread_basecolor"] = float(spread.per_channel[:3].mean())
    figures["spread_roughness"] = float(spread.per_channel[3])
    figures["spread_metallic"] = float(spread.per_channel[4])
    figures["spread_points"], figures["views_per_point"] = spread.points, spread.mean_views
    return figures


def fmt(value: float) -> str:
    return "inf" if math.isinf(value) else f"{value:.2f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a `matspray synth` object folder")
    parser.add_argument("--split", choices=("train", "test"), default="train")
    parser.add_argument("--severity", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--batch-size", type=int, default=8)
    args = parser.parse_args(argv)
    if not args.data.exists():
        print(
            f"{args.data} does not exist. Create a synthetic object with ground truth first: `matspray synth` "
            f"(see `matspray synth --help`) writing to {args.data}, then rerun this benchmark.",
            file=sys.stderr,
        )
        return 2
    try:
        scene = load_scene(args.data)
        views = scene.split(args.split)
        check_ground_truth(views, ("basecolor", "roughness", "metallic", "depth"))
        truths = {v.name: read_ground_truth(v) for v in views}
        depths = {v.name: read_ground_truth_depth(v) for v in views}
        rows = []
        for label, spec, options in (
            ("ground-truth", "ground-truth", PredictorOptions()),
            (
                f"simulated (severity {args.severity:g})",
                "simulated",
                PredictorOptions(severity=args.severity, seed=args.seed, batch_size=args.batch_size),
            ),
        ):
            start = time.perf_counter()
            predicted = predict_views(views, make_predictor(spec, options))
            seconds = time.perf_counter() - start
            rows.append((label, evaluate(views, predicted, truths, depths), seconds))
    except MatsprayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    first = views[0]
    print(
        f"\nobject: {args.data} ({len(views)} {args.split} views, {first.width}x{first.height} px; "
        f"simulated: seed {args.seed}, batches of {args.batch_size})"
    )
    print("PSNR in dB over object pixels (base color sRGB-encoded); spread = mean per-point std across views\n")
    header = (
        f"{'predictor':<24} {'PSNR base':>9} {'PSNR rough':>10} {'PSNR metal':>16}   "
        f"{'spread base':>11} {'spread rough':>12} {'spread metal':>12}"
    )
    print(header)
    print("-" * len(header))
    for label, f, _ in rows:
        metal = fmt(f["psnr_metallic"]) + (
            f" ({f['infinite_metallic']} inf)" if f["infinite_metallic"] and math.isfinite(f["psnr_metallic"]) else ""
        )
        print(
            f"{label:<24} {fmt(f['psnr_basecolor']):>9} {fmt(f['psnr_roughness']):>10} {metal:>16}   "
            f"{f['spread_basecolor']:>11.4f} {f['spread_roughness']:>12.4f} {f['spread_metallic']:>12.4f}"
        )
    f = rows[-1][1]
    print(
        f"\nspread measured on {f['spread_points']} surface points, "
        f"seen by {f['views_per_point']:.1f} views on average; "
        f"simulated predictions took {rows[-1][2]:.2f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
