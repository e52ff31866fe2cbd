"""Which views should count for a Gaussian? Lifts the TRUE material maps of a `matspray synth` object
onto a run's Gaussians, then prints
  1. how often a view's median disagrees with the Gaussian's other views (any channel of base color off
     by > 0.1 from the median over its views), by the view's share of the Gaussian's best-view hits;
  2. the Proj. Average material PSNR on the test views when only views with at least `min_support`
     of the best view's hits count (`LiftConfig.min_support`; 0 counts every view with a hit).
With true maps every disagreement is an error of the lifting, not of a predictor.

    python -m benchmarks.lift_support [--out runs/demo-demo] [--support 0 0.1 0.25 0.5 0.75]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.eval.run_eval import evaluate_asset, read_view_truth
from matspray.geometry.ply import read_ply
from matspray.method.asset import Asset
from matspray.method.lift import LiftConfig, lift, supported_views
from matspray.method.merger import projection_average
from matspray.predictors import maps_to_tensor
from matspray.predictors.ground_truth import read_ground_truth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--out", type=Path, default=Path("runs/demo-demo"), help="folder with data/ and run/ (a demo's output)"
    )
    parser.add_argument("--samples", type=int, default=LiftConfig.samples_per_side)
    parser.add_argument("--support", type=float, nargs="+", default=[0.0, 0.1, 0.25, 0.5, 0.75])
    args = parser.parse_args()
    scene = load_scene(args.out / "data")
    gaussians, normals = read_ply(args.out / "run" / "geometry" / "gaussians.ply")
    start = time.perf_counter()
    maps = [maps_to_tensor(read_ground_truth(view)) for view in scene.train]
    lifted = lift(
        gaussians,
        [v.camera for v in scene.train],
        maps,
        [v.alpha for v in scene.train],
        [v.name for v in scene.train],
        LiftConfig(samples_per_side=args.samples, min_support=0.0),
        progress=True,
    )
    print(
        f"{len(gaussians)} Gaussians ({int(lifted.kept.sum())} hit), {len(scene.train)} views, "
        f"{args.samples}x{args.samples} rays/pixel, "
        f"lifted in {time.perf_counter() - start:.0f} s"
    )
    kept, kept_normals = gaussians.subset(lifted.kept), normals[lifted.kept]
    hits, values = lifted.hits.float(), lifted.values
    hit = hits > 0
    consensus = (
        torch.where(hit[..., None], values, torch.full_like(values, float("nan"))).nanmedian(dim=1).values
    )  # [N, 5]
    off = (values[..., :3] - consensus[:, None, :3]).abs().amax(-1) > 0.1  # [N, V]
    share = hits / hits.amax(1, keepdim=True)
    print("\nshare of best-view hits   (G, view) pairs   base color off by > 0.1")
    for low, high in [(0.0, 0.1), (0.1, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.01)]:
        pairs = hit & (share > low) & (share <= high) if low > 0 else hit & (share <= high)
        print(f"{low:>10.2f} - {min(high, 1.0):<10.2f}{int(pairs.sum()):>14d}{float(off[pairs].float().mean()):>26.1%}")
    truths = [read_view_truth(v) for v in scene.test]
    print("\nmin_support   views per Gaussian   Proj. Average PSNR on test views: base color / roughness / metallic")
    for support in args.support:
        seen = supported_views(lifted.hits, support)
        asset = Asset(kept, projection_average(values, seen), kept_normals)
        psnr = {
            name: m["psnr"]
            for name, m in evaluate_asset(asset, scene.test, truths, {}, None)["summary"].items()
            if "psnr" in m
        }
        print(
            f"{support:>11.2f}{float(seen.sum(1).float().mean()):>21.1f}   "
            f"{psnr['basecolor']:.2f} / {psnr['roughness']:.2f} / {psnr['metallic']:.2f}"
        )


if __name__ == "__main__":
    main()
