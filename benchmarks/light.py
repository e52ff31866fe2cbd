"""The estimated light with and without its smoothness prior, and by light model (the figures).

For each light model (`refine.light_model`) and prior weight, refines the full method on a `matspray synth` object
(predict, geometry, lift and visibility are computed once, in OUT/base, and copied) and prints
  - tv ratio: total variation of the estimate's log radiance over that of the true training light,
    resampled to the estimate's size (target <= 1.5);
  - irradiance r: correlation of the two lights' order-2 SH irradiance (target >= 0.95);
  - relighting PSNR / SSIM of the full asset under the held-out lights (must not drop with the prior).

    python -m benchmarks.light --data runs/demo-demo/data --out runs/light-demo --weights 0 0.001 0.01
    python -m benchmarks.light --data DATA --out runs/light-models --preset test --models latlong sg --weights 3e-4
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from benchmarks.ceilings import read_test_truth
from matspray.eval.light import light_figures, training_light
from matspray.eval.run_eval import evaluate_asset
from matspray.method.asset import ENVMAP_FILE, read_asset
from matspray.method.config import METHODS, build_config
from matspray.method.pipeline import Pipeline
from matspray.presets import asset_stage
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import share_stage

SHARED_STAGES = ("materials2d", "geometry", "lift", "visibility")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a `matspray synth` object")
    parser.add_argument("--out", type=Path, required=True, help="folder for the runs (OUT/base, OUT/tv-WEIGHT)")
    parser.add_argument("--geometry-from", type=Path, help="a run folder of the same object whose geometry/ to reuse")
    parser.add_argument("--preset", default="demo", choices=("test", "demo"))
    parser.add_argument("--method", default="matspray", choices=METHODS)
    parser.add_argument("--weights", type=float, nargs="+", default=[0.0, 1e-3], help="prior weights to compare")
    parser.add_argument("--models", nargs="+", default=["latlong"], help="light models to compare (refine.light_model)")
    args = parser.parse_args()

    base = args.out / "base"
    if args.geometry_from is not None:
        share_stage(args.geometry_from, base, "geometry")
    views, truths, lights = read_test_truth(args.data)
    truth_name, truth_map = training_light(args.data)
    rows = []
    for model, weight in ((model, weight) for model in args.models for weight in args.weights):
        start = time.perf_counter()
        run = args.out / (f"tv-{weight:g}" if model == "latlong" else f"{model}-tv-{weight:g}")
        for stage in SHARED_STAGES:
            share_stage(base, run, stage)
        settings = {"refine.light_tv_weight": weight, "refine.light_model": model}
        config = build_config(args.preset, args.method, predictor="simulated", **settings)
        Pipeline(args.data, run, config, log=lambda _: None).refine("full")
        for stage in SHARED_STAGES:  # what this weight's run computed first, the next ones reuse
            share_stage(run, base, stage)
        folder = run / asset_stage("full")
        estimate = EnvironmentMap.from_file(folder / ENVMAP_FILE).map.detach()
        light = light_figures(estimate, truth_map)
        summary = evaluate_asset(read_asset(folder), views, truths, lights, None)["summary"]["relighting"]
        rows.append((model, weight, light, summary, time.perf_counter() - start))
    print(
        f"\nobject {args.data}, method {args.method}, preset {args.preset}; true training light: {truth_name}; "
        f"held-out lights: {', '.join(lights)}"
    )
    header = f"{'model':>8}{'tv weight':>10}{'tv ratio':>10}{'irradiance r':>14}{'relight PSNR':>14}{'SSIM':>8}"
    print(f"{header}{'seconds':>9}")
    for model, weight, light, summary, seconds in rows:
        print(
            f"{model:>8}{weight:>10g}{light['tv_ratio']:>10.2f}{light['irradiance_correlation']:>14.3f}{summary['psnr']:>14.2f}"
            f"{summary['ssim']:>8.3f}{seconds:>9.0f}"
        )


if __name__ == "__main__":
    main()
