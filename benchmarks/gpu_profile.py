"""Where a unit's time goes on a GPU: wall time against the kernels' time, and the kernels and operations that cost
most, per Gaussian Splatting step, per refinement step and per lifted view (torch's profiler, CUDA activity).

    python -m benchmarks.gpu_profile --data DIR [--device cuda] [--geometry-steps 4000 | --gaussians FILE]
                                     [--steps 200] [--views 6] [--units geometry refine lift] [--out DIR]

On a `matspray synth` object at the paper preset's settings (backend gsplat on CUDA when it loads): Gaussian
Splatting is trained `--geometry-steps` steps (the paper schedule stretched, densification included); then
  - Gaussian Splatting steps after densification, as `benchmarks.unit_rates --compare-eager` runs them;
  - refinement steps of `full` on random lifted values (`step_cost.random_refine_inputs`);
  - lifted views at 16 x 16 rays per pixel.
Per unit, printed and written to OUT/profile.txt: the wall time per unit (timed without the profiler), the kernels'
time per unit (the sum of their device time under the profiler, one stream), their ratio (how busy the GPU is), and
the 20 kernels and the 20 operations with the most time. A GPU that is busy far less than 100 % waits on Python and
launches; one near 100 % is bounded by its kernels. OUT also gets a chrome trace of a few units of each (gzip).
"""

from __future__ import annotations

import argparse
import gzip
import shutil
from dataclasses import replace
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from benchmarks.step_cost import random_refine_inputs
from benchmarks.unit_rates import geometry_rate, load_gaussians, steps_after_densification, synchronized_seconds
from matspray.data.loader import load_scene
from matspray.device import resolve_device
from matspray.geometry.train import prepare_views
from matspray.method.config import build_config
from matspray.method.lift import lift
from matspray.method.refine.loop import refine
from matspray.render.backend import rendering_with, resolve_backend


def refine_steps(gaussians, views, device):
    inputs = random_refine_inputs(gaussians, views, device)
    base = build_config("paper").refine

    def run(n: int) -> None:
        refine(inputs, replace(base, light_warmup=1, iterations=n, log_every=10**9), progress=False)

    return run


def lift_views(gaussians, views):
    generator = torch.Generator().manual_seed(0)
    config = build_config("paper").lift
    device = gaussians.device
    maps = [torch.rand(v.height, v.width, 5, generator=generator).to(device) for v in views]

    def run(n: int) -> None:
        chosen = [i % len(views) for i in range(n)]
        lift(gaussians, [views[i].camera for i in chosen], [maps[i] for i in chosen], [views[i].alpha for i in chosen],
             [f"{views[i].name}-{k}" for k, i in enumerate(chosen)], config, progress=False)  # fmt: skip

    return run


def profiled(device, run, units: int, trace: Path | None):
    """The profile of `run(units)`, with its chrome trace gzipped to `trace`."""
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        run(units)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    if trace is not None:
        raw = trace.with_suffix("")
        prof.export_chrome_trace(str(raw))
        with open(raw, "rb") as src, gzip.open(trace, "wb") as dst:
            shutil.copyfileobj(src, dst)
        raw.unlink()
    return prof


def device_time(event) -> float:  # microseconds of a kernel (or copy, or fill) on the device; 0 for a CPU operation
    if getattr(event, "device_type", None) != DeviceType.CUDA:
        return 0.0  # an operation's device time is its kernels', which are counted as themselves
    return getattr(event, "self_device_time_total", None) or getattr(event, "self_cuda_time_total", 0.0)


def report(name: str, device, run, units: int, profile_units: int, out: Path) -> str:
    run(max(2, units // 10))  # warm: captures, caches, compilation
    wall = synchronized_seconds(device, lambda: run(units)) / units
    prof = profiled(device, run, profile_units, out / f"trace_{name.split()[0]}.json.gz")
    averages = prof.key_averages()
    kernels = sum(device_time(e) for e in averages) / profile_units / 1e3  # ms per unit
    lines = [f"== {name}: {wall * 1e3:.2f} ms per unit (wall, {units} units), kernels {kernels:.2f} ms per unit "
             f"({100 * kernels / (wall * 1e3):.0f} % busy)"]  # fmt: skip
    by_device = sorted(averages, key=device_time, reverse=True)[:20]
    lines.append("   kernel (top 20 by device time): ms per unit, calls per unit")
    lines += [f"   {device_time(e) / profile_units / 1e3:8.3f} {e.count / profile_units:7.1f}  {e.key[:110]}"
              for e in by_device if device_time(e) > 0]  # fmt: skip
    by_cpu = sorted(averages, key=lambda e: e.self_cpu_time_total, reverse=True)[:20]
    lines.append("   operation (top 20 by its own CPU time): ms per unit, calls per unit")
    lines += [f"   {e.self_cpu_time_total / profile_units / 1e3:8.3f} {e.count / profile_units:7.1f}  {e.key[:110]}"
              for e in by_cpu]  # fmt: skip
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a `matspray synth` object")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--geometry-steps", type=int, default=4000)
    parser.add_argument("--gaussians", type=Path, help="profile on these saved Gaussians "
                        "(`unit_rates --save-gaussians`) instead of training them")  # fmt: skip
    parser.add_argument("--steps", type=int, default=200, help="Gaussian Splatting and refinement steps timed")
    parser.add_argument("--views", type=int, default=6, help="views lifted (timed)")
    parser.add_argument("--units", nargs="+", choices=("geometry", "refine", "lift"),
                        default=["geometry", "refine", "lift"])  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("runs/gpu-profile"))
    args = parser.parse_args()
    device = resolve_device(args.device)
    backend = resolve_backend("auto", device)
    scene = load_scene(args.data)
    config = build_config("paper", **{"geometry.iterations": args.geometry_steps}).geometry
    args.out.mkdir(parents=True, exist_ok=True)
    texts = []
    with rendering_with(backend):
        name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
        if args.gaussians:
            gaussians = load_gaussians(args.gaussians, device)
            head = f"{name}, backend {backend}: {len(gaussians)} Gaussians from {args.gaussians}"
        else:
            rate, gaussians = geometry_rate(scene, config, device, args.out / "geometry")
            head = (f"{name}, backend {backend}: {len(gaussians)} Gaussians after {args.geometry_steps} steps "
                    f"({rate:.1f} steps/s with densification)")  # fmt: skip
        print(head, flush=True)
        texts.append(head)
        views = [v.to(device) for v in prepare_views(scene.train, config.resolution)]
        if "geometry" in args.units:
            run = steps_after_densification(gaussians, views, config, device)
            texts.append(report("Gaussian Splatting step", device, run, args.steps, 20, args.out))
        if "refine" in args.units:
            run = refine_steps(gaussians, views, device)
            texts.append(report("refinement call of 20 steps", device, lambda n: [run(20) for _ in range(n)],
                                max(2, args.steps // 20), 2, args.out))  # fmt: skip
            calls = {n: synchronized_seconds(device, lambda n=n: run(n)) for n in (20, 20 + args.steps)}
            per_step = (calls[20 + args.steps] - calls[20]) / args.steps
            texts.append(f"refinement per step (two calls, {args.steps} steps apart): {per_step * 1e3:.2f} ms")
            print(texts[-1], flush=True)
        if "lift" in args.units:
            texts.append(report("lifted view", device, lift_views(gaussians, views), args.views, 2, args.out))
    (args.out / "profile.txt").write_text("\n".join(texts) + "\n")


if __name__ == "__main__":
    main()
