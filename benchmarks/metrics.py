"""Time the image metrics: milliseconds per image pair for PSNR, SSIM and LPIPS.

    python -m benchmarks.metrics [--sizes 128 512] [--repeats 5] [--device cpu] [--lpips-weights PATH]

Prints one line per metric and size: the median over `repeats` timed calls after one warm-up call.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from matspray.eval import load_lpips, psnr, ssim


def median_ms(function, pred, target, repeats: int) -> float:
    function(pred, target)  # warm-up (allocations, CUDA kernels)
    times = []
    for _ in range(repeats):
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        start = time.perf_counter()
        function(pred, target)
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 512])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--lpips-weights", default=None)
    args = parser.parse_args()

    lpips, source = load_lpips(args.lpips_weights)
    print(f"device {args.device}, torch threads {torch.get_num_threads()}, LPIPS: {source}")
    metrics = {"PSNR": psnr, "SSIM": ssim, **({"LPIPS": lpips.distance} if lpips is not None else {})}
    generator = torch.Generator().manual_seed(0)
    for size in args.sizes:
        pred = torch.rand(size, size, 3, generator=generator).to(args.device)
        target = torch.rand(size, size, 3, generator=generator).to(args.device)
        for name, function in metrics.items():
            print(f"{size}x{size}  {name:5s} {median_ms(function, pred, target, args.repeats):8.2f} ms")


if __name__ == "__main__":
    main()
