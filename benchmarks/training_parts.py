"""Timing of the CPU parts of a training step besides the rasterizer, and of compiling backend numba's kernels:

  - the D-SSIM loss (`ssim_loss`, every photometric loss of geometry training and refinement), forward + backward,
    on random images of each --sizes;
  - SH colour with backend numba (`sh_colors`, degree 3), forward + backward, at each --gaussians;
  - the normals of a training render (`oriented_normals`) forward + backward, torch's and numba's, at each
    --gaussians;
  - with --compile, `ensure_compiled` in a fresh process with an empty numba cache (what a fresh install pays
    once), --compile-runs times.

Best and median of --repeats, milliseconds (seconds for the compilation), with --threads torch threads (numba takes
as many). Wall time of one process: run it on a quiet machine, and note OMP_WAIT_POLICY (printed): with PASSIVE,
torch's idle threads sleep after every operation, which makes many small operations slower.

    python -m benchmarks.training_parts [--sizes 128 256] [--gaussians 20000 100000] [--threads 2] [--repeats 20]
                                        [--compile] [--compile-runs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.rasterize import interleaved_ms, sphere_object
from matspray.data.camera import Camera
from matspray.geometry.normals import oriented_normals
from matspray.metrics import ssim_loss
from matspray.render.backend import rendering_with
from matspray.render.shade.sh import sh_colors


def milliseconds(step, repeats: int) -> tuple[float, float]:
    """Best and median wall milliseconds of `step()` over `repeats` calls, after one warm-up call."""
    times = interleaved_ms({"step": step}, repeats)["step"]
    return min(times), statistics.median(times)


def compile_report() -> None:
    """Compile every kernel (in a process whose numba cache is empty) and print, as one JSON line, the total seconds
    and the seconds per kernel of matspray (a kernel's time includes the matspray kernels compiled within it)."""
    from numba.core import event

    from matspray.render.numba.backend import ensure_compiled

    start = time.perf_counter()
    with event.install_recorder("numba:compile") as recorder:
        ensure_compiled(np.float32)
    total = time.perf_counter() - start
    begun, parts = {}, {}
    for stamp, ev in recorder.buffer:
        function = ev.data["dispatcher"].py_func
        if not function.__module__.startswith("matspray"):
            continue
        name = function.__module__.rsplit(".", 1)[-1] + "." + function.__name__
        if ev.is_start:
            begun[name] = stamp
        else:
            parts[name] = parts.get(name, 0.0) + stamp - begun[name]
    print(json.dumps({"total": total, "parts": parts}))


def ssim_step(size: int):
    g = torch.Generator().manual_seed(size)
    pred = torch.rand(size, size, 3, generator=g).requires_grad_(True)
    target = torch.rand(size, size, 3, generator=g)

    def step():
        pred.grad = None
        ssim_loss(pred, target).backward()

    return step


def per_gaussian_step(n: int, backend: str, colour_of, leaves: tuple[str, ...]):
    """A step that backpropagates a weighted sum of `colour_of(gaussians, camera)` [N, 3] (SH colour, normals) through
    the sphere object of benchmarks.rasterize, rendering with `backend`, into the Gaussians' tensors `leaves`."""
    gaussians = sphere_object(n)
    for name in leaves:
        getattr(gaussians, name).requires_grad_(True)
    camera = Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.7, 128, 128)
    weights = torch.rand(n, 3, generator=torch.Generator().manual_seed(n))

    def step():
        for name in leaves:
            getattr(gaussians, name).grad = None
        with rendering_with(backend):
            (colour_of(gaussians, camera) * weights).sum().backward()

    return step


def compile_seconds() -> tuple[float, dict[str, float]]:
    """Seconds to compile every kernel in a fresh process with an empty cache, and per kernel of matspray (a kernel's
    time includes the matspray kernels it calls, compiled within it)."""
    with tempfile.TemporaryDirectory(prefix="matspray-numba-cache-") as cache:
        done = subprocess.run(
            [sys.executable, "-c", "from benchmarks.training_parts import compile_report; compile_report()"],
            env=dict(os.environ, NUMBA_CACHE_DIR=cache),
            cwd=Path(__file__).resolve().parents[1],
            capture_output=True,
            text=True,
            check=True,
        )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return result["total"], result["parts"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="*", default=[128, 256], help="image sides of the SSIM loss")
    parser.add_argument("--gaussians", type=int, nargs="*", default=[20000, 100000], help="Gaussians of SH colour")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--compile", action="store_true", help="also time compiling the kernels from scratch")
    parser.add_argument("--compile-runs", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"threads {torch.get_num_threads()}; OMP_WAIT_POLICY {os.environ.get('OMP_WAIT_POLICY', 'unset')}; "
        f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    for size in args.sizes:
        best, median = milliseconds(ssim_step(size), args.repeats)
        print(f"  D-SSIM loss, {size}x{size} px, forward+backward: {best:.2f} ms (median {median:.2f})")
    for n in args.gaussians:
        best, median = milliseconds(per_gaussian_step(n, "numba", sh_colors, ("sh", "means")), args.repeats)
        print(f"  SH colour (numba, degree 3), {n} Gaussians, forward+backward: {best:.2f} ms (median {median:.2f})")
    for n in args.gaussians:
        for backend in ("torch", "numba"):
            step = per_gaussian_step(n, backend, oriented_normals, ("quats",))
            best, median = milliseconds(step, args.repeats)
            print(
                f"  oriented normals ({backend}), {n} Gaussians, forward+backward: {best:.2f} ms (median {median:.2f})"
            )
    if args.compile:
        runs = [compile_seconds() for _ in range(args.compile_runs)]
        print(f"  numba kernels compiled from an empty cache: {', '.join(f'{total:.1f}' for total, _ in runs)} s")
        parts = sorted(runs[0][1].items(), key=lambda item: -item[1])
        print("    by kernel (first run): " + ", ".join(f"{name} {seconds:.1f}" for name, seconds in parts) + " s")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
