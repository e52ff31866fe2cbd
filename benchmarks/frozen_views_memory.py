"""Refinement's frozen views on the CPU, with and without the transposes of their blend matrices: bytes kept and
milliseconds per blend (forward and backward) at stitch's refinement scaled down.

    MATSPRAY_THREADS=1 python -m benchmarks.frozen_views_memory [--views 24] [--resolution 256]
                                                                [--gaussians 32000] [--channels 8]

A shell of `--gaussians` random Gaussians (radii 0.8 to 1 of a unit sphere, sizes and opacities such that a view
blends about 34 weights per pixel, stitch's 33) seen by `--views` cameras on a sphere. The frozen views are made as
refinement makes them (FrozenViews, backend numba's weights), which on the CPU keep one matrix per view; the old way
kept each view's transpose too, made here view by view for its timing. Per view: the forward product and the backward
pass of `--channels` features, the old one (the product with the transpose) and the new one (numba.sparse's scatter),
the fastest of `--repeats` after one untimed; printed: the bytes kept each way, the ms per view of each, the largest
difference of the gradients, and the load average (the machine may be shared: the times are CPU times of this
process as well as wall-clock ones).
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from matspray.device import configure_threads
from matspray.gaussians import Gaussians
from matspray.render.backend import rendering_with
from matspray.render.raster.gbuffer import FrozenViews, SparseBlend, blend_matrix, frozen_views_bytes, hits_of_view
from tests.scenes import sphere_cameras


def shell(count: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    means = directions * (0.8 + 0.2 * torch.rand(count, 1, generator=g))
    log_scales = torch.log(0.02 + 0.05 * torch.rand(count, 3, generator=g))
    opacities = 0.1 + 0.8 * torch.rand(count, generator=g)
    quats = torch.randn(count, 4, generator=g)
    return Gaussians(means, log_scales, quats, torch.logit(opacities), torch.zeros(count, 1, 3))


def timed(function, repeats: int) -> tuple[float, float]:  # -> fastest (wall ms, CPU ms), after one call untimed
    function()
    best = (float("inf"), float("inf"))
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        function()
        best = min(best, ((time.perf_counter() - wall) * 1e3, (time.process_time() - cpu) * 1e3))
    return best


def blend(features: torch.Tensor, upstream: torch.Tensor, matrix, transposed) -> torch.Tensor:  # -> grad [N, C]
    leaf = features.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(SparseBlend.apply(leaf, matrix, transposed), leaf, upstream)
    return grad


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--gaussians", type=int, default=32_000)
    parser.add_argument("--channels", type=int, default=8, help="features blended (refinement's: 8 or 14)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    threads = configure_threads(torch.device("cpu"))
    load = os.getloadavg()[0]
    gaussians, cameras = shell(args.gaussians), sphere_cameras(args.views, args.resolution)
    with rendering_with("numba"):
        frozen = FrozenViews(gaussians, cameras)
    pixels, n = args.resolution**2, args.gaussians
    g = torch.Generator().manual_seed(1)
    features = torch.rand(n, args.channels, generator=g)
    upstream = torch.rand(pixels, args.channels, generator=g)
    old, new, difference = [0.0, 0.0], [0.0, 0.0], 0.0
    for index, camera in enumerate(cameras):
        gaussian_ids, pixel_ids, weights = hits_of_view(gaussians, camera, "numba")
        transposed = blend_matrix(pixel_ids, gaussian_ids, weights, n, pixels)  # what the old way kept too
        matrix = frozen.matrices[index]
        for total, kept in ((old, transposed), (new, None)):
            wall, cpu = timed(lambda kept=kept: blend(features, upstream, matrix, kept), args.repeats)
            total[0], total[1] = total[0] + wall / args.views, total[1] + cpu / args.views
        grads = [blend(features, upstream, matrix, kept) for kept in (transposed, None)]
        difference = max(difference, float((grads[0] - grads[1]).abs().max() / grads[0].abs().max()))
        del transposed
    before = frozen_views_bytes(frozen.hits, pixels, n, args.views, transposed=True)
    print(
        f"{args.views} views of {args.resolution}x{args.resolution} px, {n} Gaussians, {args.channels} channels, "
        f"{threads} thread(s); {frozen.hits} weights ({frozen.hits / pixels / args.views:.1f} per pixel); "
        f"load average {load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    )
    print(f"  kept: {before / 2**20:.1f} MiB with the transposes, {frozen.kept_bytes / 2**20:.1f} MiB without")
    for name, (wall, cpu) in (("with the transposes", old), ("without (numba scatter)", new)):
        print(f"  forward + backward per view, {name}: {wall:.1f} ms wall, {cpu:.1f} ms CPU")
    print(f"  largest difference of the gradients, relative to the largest: {difference:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
