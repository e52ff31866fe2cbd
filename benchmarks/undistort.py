"""Geometry on a distorted capture against geometry on its undistorted original.

    python -m benchmarks.undistort [--res 64] [--supersample 4] [--views 20] [--test-views 5] [--iterations 1000]
                                   [--k1 -0.12 --k2 0.03 --p1 0.002 --p2 -0.001] [--threads N]

Makes a `matspray synth` object (composite shape, seed 0; rendered at res x supersample, cached in
$TMPDIR). The original capture is that object shrunk to `res`; the distorted capture is a nerfstudio
copy whose photos and masks went through an OPENCV lens with the given distortion at the fine size and
were then shrunk (as a camera with that lens would photograph it; same poses, same train/test split).
Fits geometry (preset demo at the object's resolution, the given iterations)
to both. The distorted copy is undistorted by the loader, so its views are pinhole views with a
slightly wider field of view. Prints the test PSNR of each fit on its own test views, and of the fit to
the distorted copy rendered at the original test cameras (the same pixels as the original's figure).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from matspray.data import load_scene, write_blender
from matspray.data.formats.nerfstudio import write_nerfstudio
from matspray.data.undistort import Lens, distort_view
from matspray.geometry.config import preset
from matspray.geometry.evaluate import evaluate_views
from matspray.geometry.train import train_geometry
from matspray.synth import SynthConfig, make_object


def fit(data: Path, out: Path, iterations: int, resolution: int) -> tuple[dict, object, float]:
    scene = load_scene(data)
    config = preset("demo", iterations=iterations, resolution=resolution)
    start = time.perf_counter()
    gaussians = train_geometry(scene, config, out / "geometry", restart=True, progress=False)
    seconds = time.perf_counter() - start
    return json.loads((out / "geometry" / "metrics.json").read_text()), gaussians, seconds


def scaled_lens(lens: Lens, factor: float) -> Lens:
    """The same lens for images resized by `factor` (distortion acts on normalised coordinates: unchanged)."""
    return replace(
        lens,
        fx=lens.fx * factor,
        fy=lens.fy * factor,
        cx=lens.cx * factor,
        cy=lens.cy * factor,
        width=round(lens.width * factor),
        height=round(lens.height * factor),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--res", type=int, default=64)
    parser.add_argument("--views", type=int, default=20)
    parser.add_argument("--test-views", type=int, default=5)
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--k1", type=float, default=-0.12)
    parser.add_argument("--k2", type=float, default=0.03)
    parser.add_argument("--p1", type=float, default=0.002)
    parser.add_argument("--p2", type=float, default=-0.001)
    parser.add_argument("--supersample", type=int, default=4, help="render at res x this, distort, then shrink")
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    work = (
        Path(tempfile.gettempdir()) / f"matspray-undistort-{args.res}x{args.supersample}-{args.views}-{args.test_views}"
    )
    source_dir = work / "source"  # rendered at res x supersample, so that distorting it adds no blur of its own
    if not (source_dir / "scene.json").exists():
        make_object(
            SynthConfig(
                shape="composite",
                seed=0,
                resolution=args.res * args.supersample,
                train_views=args.views,
                test_views=args.test_views,
                spp=64,
            ),
            source_dir,
            progress=False,
            notify=lambda _: None,
        )
    source = load_scene(source_dir)
    first = source.train[0].camera
    fine = Lens.from_K(first.K, first.width, first.height, (args.k1, args.k2, args.p1, args.p2, 0.0), model="OPENCV")
    factor = 1.0 / args.supersample
    lens = scaled_lens(fine, factor)
    original_dir = Path(tempfile.mkdtemp(prefix="matspray-original-"))
    original_splits = {split: [v.scaled(factor) for v in source.split(split)] for split in ("train", "test")}
    write_blender(original_dir, original_splits)
    original = load_scene(original_dir)
    distorted_dir = Path(tempfile.mkdtemp(prefix="matspray-distorted-"))
    splits = {split: [distort_view(v, fine).scaled(factor) for v in source.split(split)] for split in ("train", "test")}
    write_nerfstudio(distorted_dir, splits, lens=lens, separate_masks=True)
    runs = Path(tempfile.mkdtemp(prefix="matspray-undistort-runs-"))
    base, _, base_seconds = fit(original_dir, runs / "original", args.iterations, args.res)
    bent, gaussians, bent_seconds = fit(distorted_dir, runs / "distorted", args.iterations, args.res)
    cross = evaluate_views(gaussians, original.test)
    scene = load_scene(distorted_dir)
    print(
        f"object: composite seed 0, {args.res} px (distorted at {args.res * args.supersample} px), "
        f"{len(original.train)} train / {len(original.test)} test views; "
        f"geometry preset demo, {args.iterations} iterations; torch threads {torch.get_num_threads()}"
    )
    print(f"lens: {lens.describe()}; " + "; ".join(scene.log))
    print(f"{'capture':<44} {'test PSNR on white':>18} {'object pixels':>14} {'seconds':>8}")
    print(f"{'original (pinhole)':<44} {base['psnr']:>15.2f} dB {base['psnr_masked']:>11.2f} dB {base_seconds:>8.0f}")
    print(
        f"{'distorted, undistorted on load (own views)':<44} {bent['psnr']:>15.2f} dB {bent['psnr_masked']:>11.2f} dB "
        f"{bent_seconds:>8.0f}"
    )
    print(
        f"{'distorted fit, at the original test cameras':<44} {cross['psnr']:>15.2f} dB "
        f"{cross['psnr_masked']:>11.2f} dB"
    )
    print(
        f"difference (original - distorted fit at original cameras): {base['psnr'] - cross['psnr']:+.2f} dB on white, "
        f"{base['psnr_masked'] - cross['psnr_masked']:+.2f} dB on the object"
    )


if __name__ == "__main__":
    main()
