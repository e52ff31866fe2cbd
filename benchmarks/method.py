"""The method on the demo object with the simulated predictor: every variant's relighting and material
quality, the raw 2D predictions' quality, and the seconds per stage.

    python -m benchmarks.method [--preset demo|test] [--out runs/bench-method] [--shape composite]

Prints one table; the figures also land in OUT/run/eval/metrics.json and OUT/run/report.html.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from matspray.demo import make_demo_object, run_object
from matspray.eval.run_eval import VARIANT_LABELS
from matspray.rundir import RunDir


def fmt(value, digits=2):
    return "—" if value is None else (f"{value:.{digits}f}" if value != float("inf") else "inf")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="demo", choices=("test", "demo"))
    parser.add_argument("--out", type=Path, default=Path("runs/bench-method"))
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    start = time.perf_counter()
    data = make_demo_object(args.out / "data", args.preset, args.shape, args.seed)
    metrics = run_object(data, args.out / "run", args.preset)
    print(f"\nobject: {args.shape} seed {args.seed}, preset {args.preset}, torch threads {torch.get_num_threads()}")
    print(f"held-out lights: {', '.join(metrics['relight_envs'])}")
    header = f"{'variant':<16}{'relight PSNR':>13}{'relight SSIM':>13}{'basecolor PSNR':>15}{'rough PSNR':>11}{'metal PSNR':>11}"
    print(header)
    for variant, result in metrics["variants"].items():
        s = result["summary"]
        print(f"{VARIANT_LABELS[variant]:<16}{fmt(s['relighting']['psnr']):>13}{fmt(s['relighting']['ssim'], 3):>13}"
              f"{fmt(s['basecolor']['psnr']):>15}{fmt(s['roughness']['psnr']):>11}{fmt(s['metallic']['psnr']):>11}")
    if "predictions_2d" in metrics:
        p = metrics["predictions_2d"]
        print(f"{'2D predictions':<16}{'':>13}{'':>13}{fmt(p['basecolor']['psnr']):>15}{fmt(p['roughness']['psnr']):>11}{fmt(p['metallic']['psnr']):>11}")
    timings = RunDir(args.out / "run").timings()
    print("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    print(f"total wall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
