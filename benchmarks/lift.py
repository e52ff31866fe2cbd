"""How many Gaussians does lifting miss? For k x k rays per pixel (k = 1, 4, 16), the fraction of the
Gaussians with non-zero rendered weight in a view that receive no material value from it, and the
seconds lifting takes per view with each tracer (torch's, and numba's compiled one: they must agree, and the
benchmark stops if they do not).

    python -m benchmarks.lift --run runs/demo-demo/run [--views 4] [--samples 1 2 4 16] [--falloff 4]

Uses the run's geometry and its 2D maps (RUN/geometry/gaussians.ply, RUN/materials2d/).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.geometry.ply import read_ply
from matspray.method.lift import LiftConfig, lift_view
from matspray.predictors import maps_to_tensor, read_materials2d
from matspray.render.backend import rendering_with
from matspray.render.raster.gbuffer import rendered_weights
from matspray.rundir import read_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=Path("runs/demo-demo/run"))
    parser.add_argument("--views", type=int, default=4, help="training views to measure (evenly spread)")
    parser.add_argument("--samples", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument(
        "--falloff", type=float, default=LiftConfig.falloff, help="lambda of eq. (2) (default: the lifting default)"
    )
    args = parser.parse_args()
    scene = load_scene(read_json(args.run / "dataset.json")["source"])
    gaussians, _ = read_ply(args.run / "geometry" / "gaussians.ply")
    step = max(1, len(scene.train) // args.views)
    views = scene.train[::step][: args.views]
    maps = read_materials2d(args.run, views)
    print(
        f"{len(gaussians)} Gaussians, {len(views)} views of {views[0].width}x{views[0].height} px, "
        f"falloff {args.falloff}"
    )
    rendered = [rendered_weights(gaussians, v.camera) > 0 for v in views]
    # "any hit": every Gaussian a ray reaches counts (the sampling question alone); "visible": the
    # default rule, hits behind an opaque front (transmittance < 0.5) do not receive the front's value
    print(
        f"{'rays/pixel':>10} {'missed, any hit':>24} {'missed, visible rule':>24} {'s/view torch':>13} "
        f"{'s/view numba':>13}"
    )
    for k in args.samples:
        missed = {0.0: 0, 0.5: 0}
        total = 0
        seconds = {"torch": 0.0, "numba": 0.0}
        for view, drawn in zip(views, rendered):
            total += int(drawn.sum())
            for threshold in missed:  # no mask: the question is whether rays find what the rasterizer draws
                config = LiftConfig(samples_per_side=k, visibility_threshold=threshold, falloff=args.falloff)
                lifted = {}
                for backend in seconds:
                    start = time.perf_counter()
                    with rendering_with(backend):
                        lifted[backend] = lift_view(
                            gaussians, view.camera, maps_to_tensor(maps[view.name]), None, config
                        )
                    seconds[backend] += time.perf_counter() - start
                if not all(torch.equal(a, b) for a, b in zip(lifted["torch"], lifted["numba"])):
                    raise SystemExit(f"benchmarks.lift: the tracers disagree on view {view.name} at {k}x{k} rays")
                missed[threshold] += int((drawn & ~lifted["torch"][1]).sum())
        cells = [f"{m / total:.3%} ({m})" for m in missed.values()]
        per_view = {b: t / len(views) / len(missed) for b, t in seconds.items()}
        print(f"{f'{k}x{k}':>10} {cells[0]:>24} {cells[1]:>24} {per_view['torch']:13.2f} {per_view['numba']:13.2f}")
    print(f"(of {total} Gaussian-view pairs with non-zero rendered weight)")


if __name__ == "__main__":
    main()
