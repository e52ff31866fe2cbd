"""Geometry training on an object: test-view PSNR, normal error, time, memory, step cost.

    python -m benchmarks.geometry [--data DATASET|demo] [--preset demo] [--iterations N] [--threads N]
                                  [--backend auto|torch|numba]

DATASET is a Blender-layout folder with `{split}/{name}_normal.exr` ground-truth normals (what
`matspray synth` writes); `--data demo` makes (once) the default demo object of `matspray demo` (composite
shape, seed 0, 128 px, 40 train / 10 test views) in $TMPDIR/matspray-demo-object. Without --data, the analytic test
object of `matspray.synth.analytic` (a sphere fused with a rounded box, baked diffuse lighting) is rendered at 128
px, 40 train and 8 test views, into $TMPDIR/matspray-analytic128 (once).

Prints: PSNR on the test views (sRGB; masked = object pixels only, full = composited on white), mean
angular error of the rendered normals on the object, training wall time, peak resident memory, the
final number of Gaussians, and forward+backward milliseconds of one training render (colour and
normals, 6 channels) at 128 px with 20k Gaussians.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.rasterize import DEMO_OBJECT, sphere_object, time_ms
from matspray.data import load_scene
from matspray.data.camera import Camera
from matspray.geometry.config import preset
from matspray.geometry.evaluate import render_view
from matspray.geometry.train import train_geometry
from matspray.render.backend import rendering_with, resolve_backend
from matspray.render.numba.backend import ensure_compiled
from matspray.synth.analytic import write_analytic_dataset

CACHE = Path(tempfile.gettempdir()) / "matspray-analytic128"


def step_milliseconds(n: int = 20000, resolution: int = 128, repeats: int = 5) -> float:

    gaussians = sphere_object(n)
    for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, gaussians.sh):
        t.requires_grad_(True)
    camera = Camera.look_at(
        [0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), resolution, resolution
    )

    def step():
        render = render_view(gaussians, camera, 3, torch.ones(3))
        (render.rgb.sum() + render.raster.features[..., 3:].sum() + render.alpha.sum()).backward()

    return time_ms(step, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=None, help="dataset folder, or 'demo' for the demo object")
    parser.add_argument("--out", type=Path, default=None, help="run folder (default: a temporary one)")
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--iterations", type=int, default=None)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default, one per core)")
    parser.add_argument(
        "--backend",
        default="auto",
        choices=("auto", "torch", "numba"),
        help="rasterizer, as `matspray run --backend` (default auto: numba on the CPU)",
    )
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    data = args.data
    if data == Path("demo"):
        from matspray.batch.demo import make_demo_object

        data = make_demo_object(DEMO_OBJECT, "demo", "composite", 0)
    if data is None:
        data = CACHE
        if not (data / "transforms_test.json").exists():
            print(f"rendering the analytic test object into {data} ...")
            write_analytic_dataset(data, train_views=40, test_views=8, resolution=128)
    scene = load_scene(data)
    overrides = {} if args.iterations is None else {"iterations": args.iterations}
    config = preset(args.preset, **overrides)
    out = args.out or Path(tempfile.mkdtemp(prefix="matspray-geometry-"))
    backend = resolve_backend(args.backend, "cpu")
    if backend == "numba":
        ensure_compiled(np.float32)  # compiled (or loaded) before the clock starts
    start = time.perf_counter()
    with rendering_with(backend):
        train_geometry(scene, config, out / "geometry", restart=True)
    wall = time.perf_counter() - start
    metrics = json.loads((out / "geometry" / "metrics.json").read_text())
    print(
        f"data: {data} ({len(scene.train)} train / {len(scene.test)} test views), preset {config.preset}, "
        f"{config.iterations} iterations, backend {backend}, torch threads {torch.get_num_threads()}"
    )
    print(f"test PSNR, object pixels (sRGB): {metrics['psnr_masked']:.2f} dB")
    print(f"test PSNR, on white (sRGB):      {metrics['psnr']:.2f} dB")
    error = metrics.get("normal_error_deg")
    print(
        f"normal mean angular error:       {'n/a (no ground-truth normals)' if error is None else f'{error:.2f} deg'}"
    )
    print(f"gaussians: {metrics['gaussians']}, training {metrics['train_seconds']:.0f} s, whole stage {wall:.0f} s")
    print(f"peak resident memory: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    with rendering_with(backend):
        print(f"one training render fwd+bwd, 128 px, 20k Gaussians: {step_milliseconds():.1f} ms")
    print(f"outputs: {out / 'geometry'}")


if __name__ == "__main__":
    main()
