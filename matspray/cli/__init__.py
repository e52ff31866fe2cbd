"""The `matspray` command: a thin layer over the library. Each subcommand lives in its own module
with `add_parser(subparsers)` and `run(args) -> int`; heavy imports happen inside `run`."""

from __future__ import annotations

import argparse
import importlib
import sys

from matspray import __version__
from matspray.errors import MatsprayError

# (module under matspray.cli, one-line help); order is the order of `matspray --help`
COMMANDS = [
    ("info", "describe a dataset folder and list every problem found"),
    ("geometry", "fit 3D Gaussians (3DGS with normals) to the photos: RUN/geometry/gaussians.ply"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="matspray",
        description="MatSpray: turn multi-view photos of an object into a relightable 3D asset "
        "(3D Gaussians with base color, roughness, metallic, plus an environment light).",
    )
    parser.add_argument("--version", action="version", version=f"matspray {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, summary in COMMANDS:
        module = importlib.import_module(f"matspray.cli.{name.replace('-', '_')}")
        sub = subparsers.add_parser(name, help=summary, description=summary)
        module.add_parser(sub)
        sub.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except MatsprayError as exc:
        print(f"matspray {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"matspray {args.command}: interrupted; finished stages are kept and a rerun resumes", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
