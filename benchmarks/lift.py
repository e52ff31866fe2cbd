"""How many Gaussians does lifting miss? For k x k rays per pixel (k = 1, 4, 16), the fraction of the
Gaussians with non-zero rendered weight in a view that receive no material value from it, and the
seconds lifting takes per view.

    python -m benchmarks.lift --run runs/demo-demo/run [--views 4] [--samples 1 2 4 16]

Uses the run's geometry and its 2D maps (RUN/geometry/gaussians.ply, RUN/materials2d/).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.geometry.ply import read_ply
from matspray.lift import LiftConfig, lift_view, rendered_weight_per_gaussian
from matspray.pipeline import maps_to_tensor
from matspray.predictors import read_materials2d
from matspray.rundir import read_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=Path("runs/demo-demo/run"))
    parser.add_argument("--views", type=int, default=4, help="training views to measure (evenly spread)")
    parser.add_argument("--samples", type=int, nargs="+", default=[1, 4, 16])
    args = parser.parse_args()
    scene = load_scene(read_json(args.run / "dataset.json")["source"])
    gaussians, _ = read_ply(args.run / "geometry" / "gaussians.ply")
    step = max(1, len(scene.train) // args.views)
    views = scene.train[::step][: args.views]
    maps = read_materials2d(args.run, views)
    print(f"{len(gaussians)} Gaussians, {len(views)} views of {views[0].width}x{views[0].height} px")
    rendered = [rendered_weight_per_gaussian(gaussians, v.camera) > 0 for v in views]
    print(f"{'rays/pixel':>10} {'missed (of rendered)':>22} {'s/view':>8}")
    for k in args.samples:
        missed = total = 0
        start = time.perf_counter()
        for view, drawn in zip(views, rendered):
            # no mask here: the question is whether rays find the Gaussians the rasterizer draws
            _, seen, _ = lift_view(gaussians, view.camera, maps_to_tensor(maps[view.name]), None, LiftConfig(samples_per_side=k))
            missed += int((drawn & ~seen).sum())
            total += int(drawn.sum())
        seconds = (time.perf_counter() - start) / len(views)
        print(f"{f'{k}x{k}':>10} {f'{missed / total:.4%} ({missed}/{total})':>22} {seconds:8.2f}")


if __name__ == "__main__":
    main()
