"""`matspray info --data DATA`."""

import argparse
from pathlib import Path


def add_parser(parser) -> None:
    parser.add_argument("--data", type=Path, help="dataset folder (Blender, nerfstudio, TensoIR or COLMAP layout)")
    parser.add_argument("data_positional", nargs="?", type=Path, help=argparse.SUPPRESS)  # the old `info DATA`
    parser.add_argument("--downscale", type=float, default=1.0, help="shrink images by this factor on load (default 1)")


def run(args) -> int:
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
