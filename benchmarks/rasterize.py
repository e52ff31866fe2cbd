"""Timing of the rasterizer backends torch and numba in one run, printed as ratios (torch / numba):

  - forward and forward+backward of `rasterize` at 20 000 Gaussians 128 px and 100 000 Gaussians 256 px, both
    with the features as given tensors (the rasterizer alone) and with them from `sh_colors` (a training render:
    SH evaluation, projection and blending);
  - with --stage-iterations N, a short Gaussian Splatting training (`train_geometry`, the demo preset with N
    iterations, the schedule scaled to them) on the demo object, once per backend;
  - with --samples, what lifting traces of one view (`lift.traced_entries`, torch, against `compiled_entries`,
    numba: every (Gaussian, pixel, core) entry its rays make) at k x k rays per pixel, 20 000 Gaussians, 128 px.

The backends take turns repeat by repeat, so that load from other processes falls on both alike; the best
(least disturbed) repeat of each is compared, the median printed beside it. Threads: --threads for torch and
numba alike (default 2; the backend gives numba as many threads as torch has).

The scene imitates a trained object: flat Gaussians on the unit sphere (scales ~0.02, one axis 10x
thinner), opacities 0.3-0.95, seen from 4 units away with a 40 degree field of view.

    python -m benchmarks.rasterize [--cases 20000:128 100000:256] [--threads 2] [--repeats 7]
                                   [--stage-iterations 300] [--samples 1 4 8]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

import torch

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.method.lift import LiftConfig, compiled_entries, footprint_alpha, traced_entries
from matspray.render.backend import rendering_with
from matspray.render.raster.rasterize import rasterize
from matspray.render.settings import RasterSettings
from matspray.render.shade.sh import sh_colors

# the demo's object, made once (benchmarks.geometry reads it too)
DEMO_OBJECT = Path(tempfile.gettempdir()) / "matspray-demo-object"

BACKENDS = ("torch", "numba")


def sphere_object(n: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    # the half-way quaternion turning +z onto the normal, so the thin third axis faces outwards
    quats = torch.stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], torch.zeros(n)], dim=-1)
    log_scales = torch.log(torch.tensor([0.02, 0.02, 0.002])) + 0.3 * torch.randn(n, 3, generator=g)
    opacity = 0.3 + 0.65 * torch.rand(n, generator=g)
    sh = torch.zeros(n, 16, 3)
    sh[:, 0] = torch.rand(n, 3, generator=g) - 0.5
    sh[:, 1:] = 0.05 * torch.randn(n, 15, 3, generator=g)
    return Gaussians(
        normals.clone(), log_scales, torch.nn.functional.normalize(quats, dim=-1), torch.logit(opacity), sh
    )


def time_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats * 1000.0


def interleaved_ms(fns: dict, repeats: int) -> dict[str, list[float]]:
    """Each function once as warm-up, then `repeats` rounds in which each runs once: {name: [ms per round]}."""
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - start) * 1000.0)
    return times


def report(label: str, times: dict[str, list[float]]) -> None:
    best = {name: min(t) for name, t in times.items()}
    median = {name: statistics.median(t) for name, t in times.items()}
    print(
        f"  {label:<34} torch {best['torch']:8.1f} ms (median {median['torch']:8.1f})   numba {best['numba']:7.1f} ms "
        f"(median {median['numba']:7.1f})   ratio {best['torch'] / best['numba']:5.1f}x (medians "
        f"{median['torch'] / median['numba']:.1f}x)"
    )


def bench_case(n: int, res: int, repeats: int) -> None:
    camera = Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), res, res)
    gaussians = sphere_object(n)
    for p in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, gaussians.sh):
        p.requires_grad_(True)
    colours = sh_colors(gaussians, camera).detach().requires_grad_(True)
    background = torch.ones(3)

    def forward(backend):
        def run():
            with torch.no_grad():
                return rasterize(gaussians, camera, colours, background, backend=backend)

        return run

    def forward_backward(backend, sh: bool):
        def run():
            out = rasterize(
                gaussians, camera, sh_colors(gaussians, camera) if sh else colours, background, backend=backend
            )
            (out.features.sum() + out.alpha.sum() + out.depth.sum()).backward()

        return run

    hits = {b: forward(b)().pixel_hits for b in BACKENDS}
    assert hits["torch"] == hits["numba"], hits  # the same blended (Gaussian, pixel) pairs
    print(f"{n} Gaussians, {res}x{res} px, {hits['torch']} blended hits:")
    report("forward", interleaved_ms({b: forward(b) for b in BACKENDS}, repeats))
    report("forward+backward", interleaved_ms({b: forward_backward(b, False) for b in BACKENDS}, repeats))
    report("forward+backward with sh_colors", interleaved_ms({b: forward_backward(b, True) for b in BACKENDS}, repeats))


def bench_stage(iterations: int) -> None:
    """The demo's Gaussian Splatting stage, shortened to `iterations`, once per backend (torch first)."""
    from matspray.batch.demo import make_demo_object
    from matspray.data import load_scene
    from matspray.geometry.config import preset
    from matspray.geometry.train import train_geometry

    scene = load_scene(make_demo_object(DEMO_OBJECT, "demo", "composite", 0))
    config = preset("demo", iterations=iterations)
    small = sphere_object(10)  # numba's kernels compiled (or loaded from its cache) before the clock starts
    rasterize(
        small,
        Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, 16, 16),
        torch.ones(10, 3),
        backend="numba",
    )
    seconds, psnr = {}, {}
    for backend in BACKENDS:
        out = Path(tempfile.mkdtemp(prefix=f"matspray-bench-{backend}-"))
        start = time.perf_counter()
        with rendering_with(backend) as use:
            train_geometry(scene, config, out / "geometry", restart=True, progress=False)
        seconds[backend] = time.perf_counter() - start
        metrics = json.loads((out / "geometry" / "metrics.json").read_text())
        psnr[backend] = metrics["psnr"]
        print(
            f"  geometry stage, backend {backend}: {seconds[backend]:.1f} s ({metrics['gaussians']} Gaussians, "
            f"test PSNR {metrics['psnr']:.2f} dB, renders {use.used()})",
            flush=True,
        )
    print(
        f"  geometry stage ({iterations} iterations of the demo preset, {config.resolution} px): "
        f"ratio {seconds['torch'] / seconds['numba']:.1f}x, PSNR difference {psnr['numba'] - psnr['torch']:+.2f} dB"
    )


def bench_lift(samples: list[int], repeats: int) -> None:
    """Lifting's tracing of one view, torch against numba, the backends taking turns."""
    gaussians = sphere_object(20000)
    camera = Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), 128, 128)
    settings = RasterSettings()
    for s in samples:
        config = LiftConfig(samples_per_side=s)
        core = footprint_alpha(gaussians.opacities, config, settings.max_alpha)
        compiled_entries(gaussians, camera, None, config, settings, core)  # compiled (or loaded) before the clock
        seconds = {"torch": [], "numba": []}
        for _ in range(repeats):
            for backend, entries in (("torch", traced_entries), ("numba", compiled_entries)):
                start = time.perf_counter()
                keys, _ = entries(gaussians, camera, None, config, settings, core)
                seconds[backend].append(time.perf_counter() - start)
        best = {backend: min(times) for backend, times in seconds.items()}
        print(
            f"  lift tracing, 20000 Gaussians, 128 px, {s}x{s} rays per pixel ({len(keys)} entries): torch "
            f"{best['torch'] * 1e3:.0f} ms, numba {best['numba'] * 1e3:.0f} ms (best of {repeats}; medians "
            f"{statistics.median(seconds['torch']) * 1e3:.0f} / {statistics.median(seconds['numba']) * 1e3:.0f}): "
            f"ratio {best['torch'] / best['numba']:.1f}x"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=["20000:128", "100000:256"], help="GAUSSIANS:RESOLUTION")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2, help="threads of torch and of numba")
    parser.add_argument(
        "--stage-iterations", type=int, default=0, help="also time this many iterations of geometry training"
    )
    parser.add_argument("--samples", type=int, nargs="*", default=[], help="rays per pixel side for lifting")
    args = parser.parse_args()
    import numba

    # numba's kernels take as many threads as torch has. (numba.set_num_threads is not called here: it would start
    # numba's OpenMP pool before the backend can make its idle threads sleep; see numba_backend.ensure_compiled)
    torch.set_num_threads(args.threads)
    print(
        f"threads: torch and numba {torch.get_num_threads()}; "
        f"OMP_WAIT_POLICY {os.environ.get('OMP_WAIT_POLICY', 'unset')}; "
        f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    for case in args.cases:
        n, res = (int(x) for x in case.split(":"))
        bench_case(n, res, args.repeats)
    if args.cases:
        print(f"numba threading layer: {numba.threading_layer()}, {numba.get_num_threads()} threads")
    if args.stage_iterations:
        bench_stage(args.stage_iterations)
    if args.samples:
        bench_lift(args.samples, args.repeats)
    print(
        f"load average at the end {os.getloadavg()[0]:.1f}; "
        f"peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0:.0f} MiB"
    )


if __name__ == "__main__":
    main()
