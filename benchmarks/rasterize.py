"""Timing of the torch rasterizer: forward and forward+backward at 128 px for 5k / 20k / 50k Gaussians,
and of `contributions` (all ray hits of one view) at 1x1 / 4x4 / 8x8 rays per pixel for 20k Gaussians.

The scene imitates a trained object: flat Gaussians on the unit sphere (scales ~0.02, one axis 10x
thinner), opacities 0.3-0.95, seen from 4 units away with a 40 degree field of view.

    python -m benchmarks.rasterize [--sizes 5000 20000 50000] [--resolution 128] [--threads 1]
                                   [--samples 1 4 8]
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import torch

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.contributions import iter_contributions
from matspray.render.rasterize import rasterize
from matspray.render.sh import sh_colors


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
    return Gaussians(normals.clone(), log_scales, torch.nn.functional.normalize(quats, dim=-1), torch.logit(opacity), sh)


def time_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats * 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 50000])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--samples", type=int, nargs="*", default=[1, 4, 8], help="rays per pixel side for contributions")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    res = args.resolution
    camera = Camera.look_at([0.0, -4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), res, res)
    print(f"resolution {res}x{res}, torch threads {torch.get_num_threads()}")
    print(f"{'gaussians':>10} {'hits':>10} {'fwd ms':>9} {'fwd+bwd ms':>11}   (wall clock, mean of --repeats)")
    for n in args.sizes:
        gaussians = sphere_object(n)
        params = [gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, gaussians.sh]
        for p in params:
            p.requires_grad_(True)
        background = torch.ones(3)

        def forward():
            with torch.no_grad():
                return rasterize(gaussians, camera, sh_colors(gaussians, camera), background)

        def forward_backward():
            out = rasterize(gaussians, camera, sh_colors(gaussians, camera), background)
            (out.features.sum() + out.alpha.sum() + out.depth.sum()).backward()
            return out

        hits = forward().num_hits
        fwd = time_ms(forward, args.repeats)
        fwd_bwd = time_ms(forward_backward, args.repeats)
        print(f"{n:>10} {hits:>10} {fwd:>9.1f} {fwd_bwd:>11.1f}")
    gaussians = sphere_object(20000)
    for s in args.samples:
        start = time.perf_counter()
        hits = sum(len(part) for part in iter_contributions(gaussians, camera, s))
        print(f"contributions, 20000 gaussians, {s}x{s} rays per pixel: {hits} hits, {time.perf_counter() - start:.2f} s")
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"peak resident memory of the process: {peak_mib:.0f} MiB")


if __name__ == "__main__":
    main()
