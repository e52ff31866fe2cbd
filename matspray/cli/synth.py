"""`matspray synth --out DIR`: a synthetic benchmark object rendered by Mitsuba 3, with ground truth
(a procedural shape, or a glTF 2.0 asset with `--asset FILE.glb|FILE.gltf`)."""

import argparse
from pathlib import Path

from matspray.cli.options import hidden_alias


def add_parser(parser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output folder (Blender layout + ground truth)")
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
        default="fit",
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
        choices=("sphere", "turntable"),
        default="sphere",
        help="where the cameras are: sphere (an even spiral over elevations -20 to 70 degrees, or 10 to 70 with "
        "--ground; default) or turntable (one ring at 20 degrees, as a turntable capture)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a different scene already in --out")


def run(args) -> int:
    from matspray.errors import ConfigError
    from matspray.synth import SynthConfig, make_object

    if args.asset is not None and args.shape is not None:
        raise ConfigError("--shape and --asset exclude each other; give one")
    config = SynthConfig(
        shape=args.shape or "random",
        asset=args.asset,
        placement=args.placement,
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
