"""Peak memory of Gaussian Splatting at the sizes of the target: 100 training views of 256 px, 100 000 Gaussians.

    python -m benchmarks.geometry_memory [--iterations 300] [--views 100] [--resolution 256]
                                         [--gaussians 100000] [--backend auto]

Renders the analytic test object (matspray.synth.analytic) once into $TMPDIR, then trains its geometry from
`--gaussians` initial points with densification capped at that count, and prints the process's peak resident memory
(everything: the views, the Gaussians and their Adam moments, the rasterizer's buffers), seconds per iteration and the
Gaussians at the end. Memory does not grow after the first densification steps at a fixed cap, so a few hundred
iterations reach the peak of a whole run."""

from __future__ import annotations

import argparse
import dataclasses
import resource
import tempfile
import time
from pathlib import Path

from matspray.data import load_scene
from matspray.device import configure_threads
from matspray.geometry.config import preset
from matspray.geometry.train import train_geometry
from matspray.render.backend import rendering_with, resolve_backend
from matspray.synth.analytic import write_analytic_dataset


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--gaussians", type=int, default=100_000)
    parser.add_argument("--backend", default="auto")
    args = parser.parse_args(argv)
    import torch

    configure_threads(torch.device("cpu"))
    data = Path(tempfile.gettempdir()) / f"matspray-analytic{args.resolution}-{args.views}"
    if not (data / "transforms_train.json").exists():
        write_analytic_dataset(data, train_views=args.views, test_views=2, resolution=args.resolution)
    scene = load_scene(data)
    config = dataclasses.replace(
        preset("demo"),
        resolution=args.resolution,
        iterations=args.iterations,
        init_points=args.gaussians,
        max_gaussians=args.gaussians,
        densify_from=50,
        densify_every=50,
        checkpoint_every=10**9,
    )
    backend = resolve_backend(args.backend, torch.device("cpu"))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    start = time.perf_counter()
    with rendering_with(backend), tempfile.TemporaryDirectory() as out:
        gaussians = train_geometry(scene, config, out, progress=False)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # Linux: KiB -> GiB
    print(
        f"geometry, {len(scene.train)} views of {args.resolution} px, "
        f"{args.gaussians} initial Gaussians (cap), {backend}: "
        f"{len(gaussians.means)} Gaussians at the end, {seconds / args.iterations:.3f} s per iteration, "
        f"peak resident memory {peak:.2f} GiB (target <= 4 GB; {before:.2f} GiB after loading the views)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
