"""A preset end to end on one object: what each stage ran on, its seconds and memory.

    python -m benchmarks.paper_scale [--backend auto|torch|gsplat] [--out DIR]   # 512 px, 100 views, one GPU
    python -m benchmarks.paper_scale --preset demo --data DIR [--variants ...]  # an object made elsewhere (synth)
    python -m benchmarks.paper_scale --dry-run                                  # the same code, test size, CPU

A `matspray synth` object of the preset's size (paper: 512 px, 100 training views) is made once, then the
ordinary pipeline (predict, geometry, lift, visibility, refine, evaluate) runs on it with the chosen
rasterizer backend. Printed: per stage, the device, the run's backend and what its render calls really ran
on (each stage's record; "rays" is lifting's torch ray tracer, "rays-numba" its compiled one), seconds per stage
(the run's timings.json), peak host memory (getrusage max RSS), peak GPU memory (CUDA only), what refinement's
frozen views keep and that size scaled to the paper's 100 views x 512 px, the number of Gaussians, relighting PSNR
and the material PSNRs of the `full` variant.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import torch

from matspray.batch.demo import make_demo_object, run_object
from matspray.device import resolve_device
from matspray.method.asset import read_asset
from matspray.method.config import build_config
from matspray.presets import asset_stage
from matspray.render.backend import BACKENDS, resolve_backend
from matspray.render.raster.gbuffer import frozen_views_bytes
from matspray.rundir import RunDir, read_json


def peak_host_mib() -> float:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


PAPER_VIEWS, PAPER_PIXELS = 100, 512 * 512
GPU_BYTES, HOST_BYTES = 24 * 2**30, 32 * 2**30  # the memory the issue asks the paper preset to fit


def stage_lines(run: RunDir) -> list[str]:
    """One line per finished stage: device, backend and the renderers its calls really used."""
    lines = []
    for record in sorted(run.root.glob("*/stage.json")):
        data = read_json(record)
        if "device" not in data:
            continue
        used = ", ".join(f"{kind} x{count}" for kind, count in data.get("renders", {}).items()) or "no rendering"
        lines.append(f"  {record.parent.name:<10} device {data['device']}, backend {data['backend']}: {used}")
    return lines


def frozen_lines(frozen: dict | None) -> list[str]:
    """What refinement's frozen views kept here, and the same hits per pixel at the paper's scale."""
    if not frozen:
        return ["  refinement kept no frozen views"]
    if frozen["backend"] == "gsplat":
        return ["  refinement keeps no blend matrices (gsplat renders each step again)"]
    per_pixel = frozen["hits"] / max(frozen["pixels"], 1)
    paper = frozen_views_bytes(
        round(per_pixel * PAPER_VIEWS * PAPER_PIXELS), PAPER_PIXELS, frozen["gaussians"], PAPER_VIEWS
    )
    where = (
        "on the GPU"
        if paper <= 0.75 * GPU_BYTES
        else "on the host, copied to the GPU view by view"
        if paper <= 0.75 * HOST_BYTES
        else "nowhere: too large"
    )
    return [
        f"  refinement's frozen views: {frozen['bytes'] / 2**20:.1f} MiB for {frozen['views']} views "
        f"({per_pixel:.1f} weights per pixel, "
        f"{frozen['views_on_host']} views on the host)",
        f"  at 100 views x 512 px with the same weights per pixel: {paper / 2**30:.2f} GiB (estimate) -> kept {where}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="test preset, tiny object, CPU: checks the code path, measures nothing of interest",
    )
    parser.add_argument("--backend", choices=BACKENDS, default="auto", help="rasterizer (default auto)")
    parser.add_argument("--out", type=Path, help="work folder (default runs/paper-scale, or runs/paper-scale-dry)")
    parser.add_argument(
        "--preset",
        choices=("demo", "paper"),
        default="paper",
        help="settings and object size (default paper: 512 px, 100 views)",
    )
    parser.add_argument(
        "--data",
        type=Path,
        help="an object made by `matspray synth` to use instead of making one (for a machine without Mitsuba)",
    )
    parser.add_argument("--variants", nargs="+", default=["full"], help="variants to refine (default full)")
    parser.add_argument("--device", default="auto", help="auto|cpu|cuda (default auto)")
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    preset, device = ("test", "cpu") if args.dry_run else (args.preset, args.device)
    out = args.out or Path("runs/paper-scale-dry" if args.dry_run else f"runs/{args.preset}-scale")
    config = build_config(preset, predictor="simulated", device=device, backend=args.backend, seed=args.seed)
    run_device = resolve_device(config.device)
    backend = resolve_backend(config.backend, run_device)  # fail before the long work
    cuda = run_device.type == "cuda"
    start = time.perf_counter()
    data = args.data if args.data else make_demo_object(out / "data", preset, args.shape, args.seed)
    synth_s = time.perf_counter() - start
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    metrics = run_object(data, out / "run", config, variants=tuple(args.variants))
    summary = metrics["variants"][args.variants[0]]["summary"]
    gaussians = len(read_asset(RunDir(out / "run").path(asset_stage(args.variants[0])), device="cpu").gaussians)
    where = args.data or f"{args.shape} seed {args.seed}"
    print(f"\npreset {preset}, backend {backend}, device {run_device}, object {where}")
    print(f"synth object: {synth_s:.1f} s (reused when already made)")
    run = RunDir(out / "run")
    print("stages (device, backend, what the render calls ran on):")
    print("\n".join(stage_lines(run)))
    print("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in run.timings().items()))
    print("\n".join(frozen_lines(read_json(run.path(asset_stage(args.variants[0]), "stage.json")).get("frozen_views"))))
    print(f"peak host memory: {peak_host_mib():.0f} MiB")
    if cuda:
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB")
    print(f"Gaussians: {gaussians}")
    print(
        f"{args.variants[0]}: relighting PSNR {summary['relighting']['psnr']:.2f} dB; material PSNR: "
        f"basecolor {summary['basecolor']['psnr']:.2f}, "
        f"roughness {summary['roughness']['psnr']:.2f}, metallic {summary['metallic']['psnr']:.2f} dB"
    )
    print(f"total wall time: {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
