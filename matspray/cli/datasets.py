"""The commands that make or describe a dataset folder, the input of every other command: `info` describes one and lists
its problems, `colmap` makes one from photos (structure from motion), `synth` renders a benchmark object with ground
truth."""

import argparse
from pathlib import Path

from matspray.cli.options import given, hidden_alias, output_folder, refuse


# `matspray info --data DATA`
def add_info_parser(parser) -> None:
    parser.add_argument("--data", type=Path, help="dataset folder (Blender, nerfstudio, TensoIR or COLMAP layout)")
    parser.add_argument("data_positional", nargs="?", type=Path, help=argparse.SUPPRESS)  # the old `info DATA`
    parser.add_argument("--downscale", type=float, default=1.0, help="shrink images by this factor on load (default 1)")


def info_main(args) -> int:
    from matspray.data import describe_scene, load_scene
    from matspray.errors import ConfigError

    args.data = args.data or args.data_positional
    if args.data is None:
        raise ConfigError("give the dataset folder: --data DATA")

    summary = describe_scene(load_scene(args.data, downscale=args.downscale))
    print("\n".join(summary.lines))
    if summary.problems:
        print(f"problems ({len(summary.problems)}):")
        for problem in summary.problems:
            print(f"  - {problem}")
    else:
        print("problems: none found")
    return 0


# `matspray colmap IMAGES --out DATASET`: structure from motion on a folder of photos (pycolmap, CPU)
MATCHERS = ("exhaustive", "sequential")  # matspray.data.sfm's (a test checks); kept here so `--help` loads no torch
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")


def add_colmap_parser(parser) -> None:
    parser.description = (
        "Estimate camera poses and intrinsics from a folder of photos with pycolmap on the CPU (SIFT features, "
        "matching, incremental mapping), undistort them, and write a dataset folder that `matspray info` and "
        "`matspray run` read. Photos: JPEG or PNG, 3 or more (20+ around the object is better). "
        "Takes about a minute for a dozen 1 MP photos on two cores; exhaustive matching grows with the square "
        "of the number of photos."
    )
    parser.add_argument("images", type=Path, help="folder of photos (JPEG or PNG; EXIF orientation is honoured)")
    parser.add_argument(
        "--out", type=output_folder, required=True, help="dataset folder to create (must not exist or be empty)"
    )
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


def colmap_main(args) -> int:
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


# `matspray synth --out DIR`: a synthetic benchmark object rendered by Mitsuba 3, with ground truth
# (a procedural shape, or a glTF 2.0 asset with `--asset FILE.glb|FILE.gltf`)
def add_synth_parser(parser) -> None:
    parser.add_argument(
        "--out", type=output_folder, required=True, help="output folder (Blender layout + ground truth)"
    )
    parser.add_argument(
        "--shape",
        default=None,
        help="sphere, rounded-cube, torus, capsule, blob, composite, or random (picked from the seed; default)",
    )
    parser.add_argument(
        "--asset",
        type=Path,
        default=None,
        metavar="FILE",
        help="render this glTF 2.0 asset (.glb, or .gltf with its files) instead of a procedural shape: every triangle "
        "primitive of its default scene with its metallic-roughness material; normal, occlusion and emissive "
        "textures and alpha are ignored (said once)",
    )
    parser.add_argument(
        "--placement",
        choices=("fit", "keep"),
        help="of --asset: fit (centred, scaled into the unit sphere; default) or keep (the file's units and origin, "
        "glTF +Y up as our +z; reproduces a synth object from its object.glb)",
    )
    parser.add_argument(
        "--object-seed",
        dest="object_seed",
        type=int,
        default=0,
        help="seed of shape, materials, cameras and renders (default 0)",
    )
    hidden_alias(parser, "--seed", "object_seed", type=int)  # the old name of --object-seed
    parser.add_argument("--resolution", type=int, default=128, help="image width and height in pixels (default 128)")
    hidden_alias(parser, "--res", "resolution", type=int)  # the old name of --resolution
    parser.add_argument("--views", type=int, default=40, help="training views (default 40)")
    parser.add_argument("--test-views", type=int, default=10, help="test views, each also relit (default 10)")
    parser.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel (default 64)")
    parser.add_argument(
        "--env",
        default="sky",
        help="training light: built-in name, .exr/.hdr lat-long file, or a packaged HDRI name "
        "(city, forest, interior, sunrise; default sky)",
    )
    parser.add_argument(
        "--relight-env",
        nargs="+",
        default=None,
        metavar="ENV",
        help="lights of the relit test views (default: two built-ins other than --env)",
    )
    # the rows the lights are resampled to for Mitsuba (default 128): a benchmark setting, not the relighting
    # commands' --env-height (the rows of the prefiltered light they shade with)
    parser.add_argument("--env-height", type=int, default=128, help=argparse.SUPPRESS)
    parser.add_argument(
        "--background",
        choices=("transparent", "env"),
        default="transparent",
        help="behind the object in the photos: transparent (alpha = the object's mask; default) or env (the training "
        "light, as a real photo shows it; the photos then carry no mask and the true masks stay in the ground truth)",
    )
    parser.add_argument(
        "--ground",
        action="store_true",
        help="a grey ground plane under the object in the photos (cameras stay above it; photos carry no mask); "
        "the relit ground truth shows the object alone",
    )
    parser.add_argument(
        "--cameras",
        choices=("sphere", "turntable", "front"),
        default="sphere",
        help="where the cameras are: sphere (an even spiral over elevations -20 to 70 degrees, or 10 to 70 with "
        "--ground; default), turntable (one ring at 20 degrees, as a turntable capture) or front (one side only: "
        "azimuths within 75 degrees of the front, elevations up to 45)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a different scene already in --out")


def synth_main(args) -> int:
    from matspray.errors import ConfigError
    from matspray.synth import SynthConfig, make_object

    if args.asset is not None and args.shape is not None:
        raise ConfigError("--shape and --asset exclude each other; give one")
    if args.asset is None:
        refuse(given(args, ("--placement",)), "for --asset (a procedural shape has no units)")
    config = SynthConfig(
        shape=args.shape or "random",
        asset=args.asset,
        placement=args.placement or "fit",
        seed=args.object_seed,
        resolution=args.resolution,
        train_views=args.views,
        test_views=args.test_views,
        spp=args.spp,
        env=args.env,
        relight_envs=args.relight_env,
        env_height=args.env_height,
        background=args.background,
        ground=args.ground,
        cameras=args.cameras,
        overwrite=args.overwrite,
    )
    result = make_object(config, args.out)
    print(
        f"{result.out}: {result.shape} under {result.train_env}, "
        f"relit under {', '.join(result.relight_envs) or 'nothing'} "
        f"({result.variant}, {result.seconds:.1f} s)"
    )
    return 0
