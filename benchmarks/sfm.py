"""`matspray colmap` on a real capture: photos registered, reprojection error, focal length against the truth, time.

    python -m benchmarks.sfm [--images ../shared/data/captures/sceaux/images] [--k K.txt] [--single-camera]
                             [--matcher exhaustive|sequential] [--max-size 1600] [--camera-model SIMPLE_RADIAL]
                             [--out DATASET]

Defaults to the 11 photos of the Sceaux facade in the shared data, whose `K.txt` holds the true pinhole
intrinsics at the photos' size. Prints the figures of `matspray colmap` and the estimated focal length
(each camera's) against K.txt, in pixels and percent.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from matspray.data.sfm import CAMERA_MODELS, MATCHERS, SfmConfig, run_sfm

SCEAUX = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "captures" / "sceaux"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=Path, default=SCEAUX / "images")
    parser.add_argument(
        "--k", type=Path, default=None, help="true intrinsics, 3x3 text (default: K.txt beside --images)"
    )
    parser.add_argument("--single-camera", action="store_true")
    parser.add_argument("--matcher", choices=MATCHERS, default="exhaustive")
    parser.add_argument("--max-size", type=int, default=1600)
    parser.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL")
    parser.add_argument("--out", type=Path, default=None, help="dataset folder (default: a new temporary one)")
    args = parser.parse_args()
    if not args.images.is_dir():
        raise SystemExit(f"{args.images}: no such folder (the shared data is not here)")
    out = args.out or Path(tempfile.mkdtemp(prefix="matspray-sfm-")) / "dataset"
    config = SfmConfig(
        matcher=args.matcher, max_size=args.max_size, single_camera=args.single_camera, camera_model=args.camera_model
    )
    result = run_sfm(args.images, out, config, progress=False, log=lambda _: None)
    print(
        f"images: {args.images} ({result.photos} photos), matcher {config.matcher}, "
        f"{'one shared camera' if config.single_camera else 'cameras as COLMAP groups them'} ({config.camera_model}), "
        f"max size {config.max_size}"
    )
    print(f"registered: {result.registered} of {result.photos} (models: {result.model_sizes})")
    print(f"mean reprojection error: {result.mean_reprojection_error:.3f} px; 3D points: {result.points}")
    print(f"seconds: {result.seconds:.1f}")
    k_path = args.k or args.images.parent / "K.txt"
    if k_path.is_file():
        true_focal = float(np.loadtxt(k_path)[0, 0])
        print(
            f"focal length: estimated {result.focal:.1f} px (mean of {len(result.cameras)} cameras), "
            f"true {true_focal:.1f} px ({k_path.name}), error {100 * (result.focal / true_focal - 1):+.2f}%"
        )
    for line in result.cameras:
        print(f"  {line}")
    for note in result.notes:
        print(f"note: {note}")
    print(f"dataset: {result.dataset}")


if __name__ == "__main__":
    main()
