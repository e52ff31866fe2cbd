"""`matspray colmap IMAGES --out DATASET`: structure from motion on a folder of photos (pycolmap, CPU)."""

from pathlib import Path

from matspray.cli.options import hidden_alias

MATCHERS = ("exhaustive", "sequential")  # matspray.data.sfm's (a test checks); kept here so `--help` loads no torch
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")


def add_parser(parser) -> None:
    parser.description = (
        "Estimate camera poses and intrinsics from a folder of photos with pycolmap on the CPU (SIFT features, "
        "matching, incremental mapping), undistort them, and write a dataset folder that `matspray info` and "
        "`matspray run` read. Photos: JPEG or PNG, 3 or more (20+ around the object is better). "
        "Takes about a minute for a dozen 1 MP photos on two cores; exhaustive matching grows with the square "
        "of the number of photos."
    )
    parser.add_argument("images", type=Path, help="folder of photos (JPEG or PNG; EXIF orientation is honoured)")
    parser.add_argument("--out", type=Path, required=True, help="dataset folder to create (must not exist or be empty)")
    parser.add_argument(
        "--matcher",
        choices=MATCHERS,
        default="exhaustive",
        help="exhaustive: every pair of photos (default; best for photos around an object); "
        "sequential: neighbours in file-name order (frames of a video)",
    )
    parser.add_argument(
        "--resolution",
        type=int,
        default=1600,
        help="shrink photos to this longest side first (default 1600)",
    )
    hidden_alias(parser, "--max-size", "resolution", type=int)  # the old name of --resolution
    parser.add_argument(
        "--masks",
        type=Path,
        default=None,
        help="folder of object masks, one per photo, same name (any of .png/.jpg); white = object",
    )
    parser.add_argument(
        "--single-camera",
        action="store_true",
        help="one camera (lens and zoom) for every photo; recommended when that is true, "
        "as photos without EXIF otherwise get a camera each",
    )
    parser.add_argument(
        "--camera-model",
        choices=CAMERA_MODELS,
        default="SIMPLE_RADIAL",
        help="lens model to estimate (default SIMPLE_RADIAL: focal length and one radial term); "
        "distorted models are undistorted when the dataset is written",
    )
    parser.add_argument("--threads", type=int, default=-1, help="pycolmap threads (default: all cores)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    from matspray.data.sfm import SfmConfig, run_sfm

    config = SfmConfig(
        matcher=args.matcher,
        max_size=args.resolution,
        single_camera=args.single_camera,
        camera_model=args.camera_model,
        threads=args.threads,
    )
    log = (lambda _: None) if args.quiet else print
    result = run_sfm(args.images, args.out, config, masks=args.masks, progress=not args.quiet, log=log)
    print(
        f"registered {result.registered} of {result.photos} photos; {result.points} points; "
        f"mean reprojection error {result.mean_reprojection_error:.3f} px; {result.seconds:.0f} s"
    )
    for line in result.cameras[:5]:
        print(f"  {line}")
    if len(result.cameras) > 5:
        print(f"  ... {len(result.cameras) - 5} more cameras; mean focal length {result.focal:.1f} px")
    for note in result.notes:
        print(f"note: {note}")
    print(
        f"dataset: {result.dataset}  (next: matspray info --data {result.dataset}; "
        f"matspray run --data {result.dataset} --out RUN)"
    )
    return 0
