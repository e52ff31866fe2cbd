"""The `paper` preset end to end on one object at paper scale (issue 24).

    python -m benchmarks.paper_scale [--backend auto|torch|gsplat] [--out DIR]   # 512 px, 100 views, one GPU
    python -m benchmarks.paper_scale --dry-run                                  # the same code, test size, CPU

A `matspray synth` object of the preset's size (paper: 512 px, 100 training views) is made once, then the
ordinary pipeline (predict, geometry, lift, visibility, refine, evaluate) runs on it with the chosen
rasterizer backend. Printed: the backend that ran, seconds per stage (the run's timings.json), peak host
memory (getrusage max RSS), peak GPU memory (CUDA only), the number of Gaussians, relighting PSNR and the
material PSNRs of the `full` variant.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import torch

from matspray.asset import read_asset
from matspray.config import build_config
from matspray.demo import make_demo_object, run_object
from matspray.device import resolve_device
from matspray.render.backend import BACKENDS, resolve_backend
from matspray.rundir import RunDir
from matspray.variants import asset_stage


def peak_host_mib() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dry-run", action="store_true", help="test preset, tiny object, CPU: checks the code path, measures nothing of interest")
    parser.add_argument("--backend", choices=BACKENDS, default="auto", help="rasterizer (default auto)")
    parser.add_argument("--out", type=Path, help="work folder (default runs/paper-scale, or runs/paper-scale-dry)")
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    preset, device = ("test", "cpu") if args.dry_run else ("paper", "auto")
    out = args.out or Path("runs/paper-scale-dry" if args.dry_run else "runs/paper-scale")
    config = build_config(preset, predictor="simulated", device=device, backend=args.backend, seed=args.seed)
    backend = resolve_backend(config.backend, resolve_device(config.device))  # fail before the long work
    cuda = torch.cuda.is_available() and not args.dry_run
    start = time.perf_counter()
    data = make_demo_object(out / "data", preset, args.shape, args.seed)
    synth_s = time.perf_counter() - start
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    metrics = run_object(data, out / "run", config, variants=("full",))
    summary = metrics["variants"]["full"]["summary"]
    gaussians = len(read_asset(RunDir(out / "run").path(asset_stage("full")), device="cpu").gaussians)
    print(f"\npreset {preset}, backend {backend}, device {resolve_device(config.device)}, object {args.shape} seed {args.seed}")
    print(f"synth object: {synth_s:.1f} s (reused when already made)")
    print("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in RunDir(out / "run").timings().items()))
    print(f"peak host memory: {peak_host_mib():.0f} MiB")
    if cuda:
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB")
    print(f"Gaussians: {gaussians}")
    print(f"relighting PSNR {summary['relighting']['psnr']:.2f} dB; material PSNR: basecolor {summary['basecolor']['psnr']:.2f}, "
          f"roughness {summary['roughness']['psnr']:.2f}, metallic {summary['metallic']['psnr']:.2f} dB")
    print(f"total wall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
