"""Per-unit rates of the paper preset on one object, and the whole preset projected from them.

    python -m benchmarks.unit_rates --data DIR [--device cuda] [--geometry-steps 7000] [--refine-steps 1000]
                                    [--warmup-steps 200] [--compare-eager 1000] [--json FILE]
                                    [--save-gaussians FILE | --gaussians FILE] [--lift-unfused]

On a `matspray synth` object (any number of views; the paper's is 100 views at 512 px), with the paper preset's
settings and the device's backend (gsplat on CUDA when it loads):
  - Gaussian Splatting: `--geometry-steps` steps with the paper schedule stretched to them (densification included),
    steps per second; with `--compare-eager N`, N steps from the trained Gaussians with and without the loss terms'
    CUDA graphs (the same steps timed both ways, densification over);
  - lifting with 16 x 16 rays per pixel: seconds per view over every training view (random maps: the time does not
    depend on their values); with `--lift-unfused` also with the rays' response by torch operations;
  - refinement of `full`: the light warm-up and the refinement steps, steps per second (each from two runs that
    differ only in its step count, so that set-up and the frozen views cancel);
  - the whole `demo --preset paper` projected from these rates (benchmarks.paper_projection: every stage and
    variant, the merger at 100 views, the paper's densification schedule, the frozen views, evaluation; a
    projection, not a measurement), each term labelled with what it was measured on.
Each figure is one run; the device's name is printed with them.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.step_cost import random_refine_inputs
from matspray.data.loader import load_scene
from matspray.device import resolve_device
from matspray.gaussians import Gaussians
from matspray.geometry.config import GeometryConfig
from matspray.geometry.densify import DensityControl
from matspray.geometry.optim import GaussianOptimizer
from matspray.geometry.train import SYNC_EVERY, learning_rates, prepare_views, scene_extent, train_geometry
from matspray.method.config import build_config
from matspray.method.lift import lift
from matspray.method.refine.loop import RefineConfig, refine
from matspray.render.backend import rendering_with, resolve_backend

GAUSSIAN_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh")


def synchronized_seconds(device: torch.device, work) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    work()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def geometry_rate(scene, config: GeometryConfig, device, out: Path) -> tuple[float, object]:
    """Steps per second of a whole geometry run (its own clock, which leaves out the final evaluation)."""
    gaussians = train_geometry(scene, config, out, device=device, restart=True, progress=False)
    metrics = json.loads((out / "metrics.json").read_text())
    return config.iterations / metrics["train_seconds"], gaussians


def steps_after_densification(gaussians, views, config: GeometryConfig, device, graphs: bool = True):
    """A function `run(n)` that trains `n` more steps from `gaussians` on `views`, from the step after densification
    on (progress read every SYNC_EVERY steps, as in training), the loss terms as CUDA graphs when `graphs`."""
    from matspray.geometry.step import ImageTerms, RunningStats, TrainingView, training_step

    extent = scene_extent(views)
    masked = all(v.alpha is not None for v in views)
    targets = [TrainingView.of(v, masked) for v in views]
    optimizer = GaussianOptimizer(gaussians, learning_rates(config, extent))
    density = DensityControl(config, extent, len(gaussians), device)
    running, terms, generator = RunningStats(device), ImageTerms(graphs), torch.Generator().manual_seed(0)
    state = {"iteration": config.densify_until + 1}

    def run(n: int) -> None:
        for _ in range(n):
            iteration = state["iteration"]
            report = (iteration + 1) % SYNC_EVERY == 0
            target = targets[iteration % len(targets)]
            training_step(optimizer, density, running, target, config, iteration, generator, terms, report)
            state["iteration"] += 1

    return run


def eager_against_graphs(gaussians, views, config: GeometryConfig, device, steps: int) -> dict[str, float]:
    """Steps per second of the same `steps` steps from the trained Gaussians (densification over), with and without
    the loss terms' CUDA graphs."""
    rates = {}
    for graphs in (True, False):
        run = steps_after_densification(gaussians, views, config, device, graphs)
        run(2 * len(views))  # every view's capture, and warm caches
        seconds = synchronized_seconds(device, lambda: run(steps))
        rates["with graphs" if graphs else "without graphs"] = steps / seconds
    return rates


def lift_seconds_per_view(gaussians, views, device, samples_per_side: int) -> float:
    generator = torch.Generator().manual_seed(0)
    maps = [torch.rand(v.height, v.width, 5, generator=generator).to(device) for v in views]
    config = replace(build_config("paper").lift, samples_per_side=samples_per_side)
    cameras, masks = [v.camera for v in views], [v.alpha for v in views]
    names = [v.name for v in views]
    lift(gaussians, cameras[:1], maps[:1], masks[:1], names[:1], config, progress=False)  # compiles, warms caches
    seconds = synchronized_seconds(device, lambda: lift(gaussians, cameras, maps, masks, names, config, progress=False))
    return seconds / len(views)


def save_gaussians(gaussians: Gaussians, path: Path) -> None:
    """The Gaussians' tensors (not the class: another version of the package reads them too)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({name: getattr(gaussians, name).detach().cpu() for name in GAUSSIAN_FIELDS}, path)


def load_gaussians(path: Path, device) -> Gaussians:
    tensors = torch.load(path, map_location="cpu")
    return Gaussians(*(tensors[name] for name in GAUSSIAN_FIELDS)).to(device)


def refine_rates(gaussians, views, device, warmup: int, steps: int) -> dict[str, float]:
    inputs = random_refine_inputs(gaussians, views, device)
    base: RefineConfig = build_config("paper").refine

    def seconds(warm: int, iterations: int) -> float:
        config = replace(base, light_warmup=warm, iterations=iterations, log_every=10**9)
        return synchronized_seconds(device, lambda: refine(inputs, config, progress=False))

    seconds(2, 2)  # first calls: kernels, caches
    short, long = max(1, warmup // 10), warmup
    warm_rate = (long - short) / (seconds(long, 1) - seconds(short, 1))
    short, long = max(1, steps // 10), steps
    refine_rate = (long - short) / (seconds(1, long) - seconds(1, short))
    return {"light warm-up": warm_rate, "refinement full": refine_rate}


def projected(figures: dict, device_name: str) -> dict:
    """The whole `demo --preset paper` projected (benchmarks.paper_projection) with these rates in place of the
    committed H200 ones, for both count curves; printed term by term."""
    from benchmarks import paper_projection

    rates = {
        **paper_projection.H200,
        "geometry_rate": figures["geometry_rate"],
        "rates_gaussians": figures["gaussians"],
        "refine_rate": figures["refinement full"],
        "warmup_rate": figures["light warm-up"],
        "lift_s_per_view": figures["lift_seconds_per_view"],
        "rates_views": figures["views"],
    }
    cpu = paper_projection.cpu_figures()
    found = {}
    for final in (paper_projection.H200["stretched_final_gaussians"], build_config("paper").geometry.max_gaussians):
        terms = paper_projection.project(cpu, final, rates, f"{device_name}, measured now (the rest: H200)")
        print(paper_projection.report(terms, final), flush=True)
        found[str(final)] = {t.stage: t.seconds for t in terms}
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a `matspray synth` object")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--geometry-steps", type=int, default=7000)
    parser.add_argument("--compare-eager", type=int, default=0, metavar="N")
    parser.add_argument("--lift-samples", type=int, default=16, help="rays per pixel side (paper: 16)")
    parser.add_argument("--warmup-steps", type=int, default=200)
    parser.add_argument("--refine-steps", type=int, default=1000)
    parser.add_argument("--out", type=Path, default=Path("runs/unit-rates"))
    parser.add_argument("--save-gaussians", type=Path, help="write the trained Gaussians' tensors here (torch.save)")
    parser.add_argument("--gaussians", type=Path, help="time lifting and refinement on these saved Gaussians "
                        "(--save-gaussians) instead of training them (then nothing is projected)")  # fmt: skip
    parser.add_argument("--lift-unfused", action="store_true",
                        help="also time lifting with the rays' response by torch operations")  # fmt: skip
    parser.add_argument("--json", type=Path)
    units = ("geometry", "lift", "refine")
    parser.add_argument("--units", nargs="+", choices=units, default=list(units),
                        help="what to time (default all; without all three nothing is projected)")  # fmt: skip
    args = parser.parse_args()
    device = resolve_device(args.device)
    backend = resolve_backend("auto", device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    scene = load_scene(args.data)
    config = build_config("paper", **{"geometry.iterations": args.geometry_steps}).geometry
    figures: dict = {"device": name, "backend": backend, "object": str(args.data), "views": len(scene.train)}
    with rendering_with(backend):
        if args.gaussians:
            rate, gaussians = None, load_gaussians(args.gaussians, device)
            figures.update(gaussians=len(gaussians), gaussians_from=str(args.gaussians))
            print(f"{name}, backend {backend}: {len(gaussians)} Gaussians from {args.gaussians}", flush=True)
        else:
            rate, gaussians = geometry_rate(scene, config, device, args.out / "geometry")
            figures.update(gaussians=len(gaussians), geometry_steps=args.geometry_steps, geometry_rate=rate)
            print(f"{name}, backend {backend}: Gaussian Splatting {rate:.1f} steps/s over {args.geometry_steps} "
                  f"steps ({len(gaussians)} Gaussians)", flush=True)  # fmt: skip
        if args.save_gaussians:
            save_gaussians(gaussians, args.save_gaussians)
        if args.compare_eager and rate is not None:
            train = [v.to(device) for v in prepare_views(scene.train, config.resolution)]
            compared = eager_against_graphs(gaussians, train, config, device, args.compare_eager)
            figures["geometry_after_densification"] = compared
            print("  after densification: " + ", ".join(f"{k} {v:.1f} steps/s" for k, v in compared.items()))
        views = [v.to(device) for v in prepare_views(scene.train, config.resolution)]
        if "lift" in args.units:
            lift_s = lift_seconds_per_view(gaussians, views, device, args.lift_samples)
            figures["lift_seconds_per_view"] = lift_s
            side = args.lift_samples
            print(f"lifting, {side}x{side} rays per pixel: {lift_s:.3f} s per view", flush=True)
            if args.lift_unfused:
                from matspray.render.rays import contributions

                contributions.FUSED[0] = False
                unfused = lift_seconds_per_view(gaussians, views, device, args.lift_samples)
                contributions.FUSED[0] = True
                figures["lift_seconds_per_view_unfused"] = unfused
                print(f"  the same with the rays' response by torch operations: {unfused:.3f} s per view", flush=True)
        if "refine" in args.units:
            rates = refine_rates(gaussians, views, device, args.warmup_steps, args.refine_steps)
            figures.update(rates)
            print(", ".join(f"{k} {v:.1f} steps/s" for k, v in rates.items()), flush=True)
    if len(args.units) == 3 and rate is not None:
        figures["paper_preset_projected"] = projected(figures, name)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
