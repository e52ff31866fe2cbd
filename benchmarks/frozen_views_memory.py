"""Refinement's frozen views on the CPU, packed (16-bit weights and columns, no transposes) and as torch's CSR
matrices with their transposes: bytes kept and milliseconds per blend (forward and backward) at stitch's refinement
scaled down.

    MATSPRAY_THREADS=1 python -m benchmarks.frozen_views_memory [--views 24] [--resolution 256]
                                                                [--gaussians 32000] [--channels 8]

A shell of `--gaussians` random Gaussians (radii 0.8 to 1 of a unit sphere, sizes and opacities such that a view
blends about 34 weights per pixel, stitch's 33) seen by `--views` cameras on a sphere. The frozen views are made as
refinement makes them (FrozenViews, backend numba's weights), which on the CPU keep one packed matrix per view; the
old way kept torch's matrix and its transpose, made here view by view for its timing. Per view: the forward product
and the backward pass of `--channels` features, the old way (torch's products) and the new (numba.sparse's gather
and scatter), the fastest of `--repeats` after one untimed; printed: the bytes kept each way, the ms per view of
each, the largest difference of the images and of the gradients (relative to the largest value), and the load
average (the machine may be shared: the times are CPU times of this process as well as wall-clock ones).
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from matspray.device import configure_threads
from matspray.gaussians import Gaussians
from matspray.render.backend import rendering_with
from matspray.render.raster.gbuffer import FrozenViews, SparseBlend, blend_matrix, frozen_views_bytes, view_blend
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


def blend(features: torch.Tensor, upstream: torch.Tensor, matrix, transposed):  # -> image [P, C], grad [N, C]
    leaf = features.detach().requires_grad_(True)
    image = SparseBlend.apply(leaf, matrix, transposed)
    (grad,) = torch.autograd.grad(image, leaf, upstream)
    return image.detach(), grad


def relative_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / a.abs().max())


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
    old, new, differences = [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]
    for index, camera in enumerate(cameras):
        crow, gaussian_ids, weights = view_blend(gaussians, camera, "numba")[:3]
        pixel_ids = torch.repeat_interleave(torch.arange(pixels), crow.diff())
        matrices = (  # what the old way kept
            blend_matrix(gaussian_ids, pixel_ids, weights, pixels, n),
            blend_matrix(pixel_ids, gaussian_ids, weights, n, pixels),
        )
        packed = (frozen.matrices[index], None)
        for total, kept in ((old, matrices), (new, packed)):
            wall, cpu = timed(lambda kept=kept: blend(features, upstream, *kept), args.repeats)
            total[0], total[1] = total[0] + wall / args.views, total[1] + cpu / args.views
        results = [blend(features, upstream, *kept) for kept in (matrices, packed)]
        for k in range(2):
            differences[k] = max(differences[k], relative_difference(results[0][k], results[1][k]))
        del matrices
    before = frozen_views_bytes(frozen.hits, pixels, n, args.views, transposed=True)
    print(
        f"{args.views} views of {args.resolution}x{args.resolution} px, {n} Gaussians, {args.channels} channels, "
        f"{threads} thread(s); {frozen.hits} weights ({frozen.hits / pixels / args.views:.1f} per pixel); "
        f"load average {load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    )
    print(f"  kept: {before / 2**20:.1f} MiB torch's with the transposes, {frozen.kept_bytes / 2**20:.1f} MiB packed")
    for name, (wall, cpu) in (("torch's with the transposes", old), ("packed (numba gather and scatter)", new)):
        print(f"  forward + backward per view, {name}: {wall:.1f} ms wall, {cpu:.1f} ms CPU")
    print(
        f"  largest difference, relative to the largest value: images {differences[0]:.1e}, "
        f"gradients {differences[1]:.1e}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
