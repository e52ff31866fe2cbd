"""The `matspray` command: a thin layer over the library. Each subcommand lives in its own module
with `add_parser(subparsers)` and `run(args) -> int`; heavy imports happen inside `run`."""

from __future__ import annotations

import argparse
import importlib
import sys

from matspray import __version__
from matspray.cli.options import flag_message
from matspray.errors import MatsprayError

# (module under matspray.cli, one-line help); order is the order of `matspray --help`
COMMANDS = [
    ("info", "describe a dataset folder and list every problem found"),
    ("colmap", "structure from motion on a folder of photos (pycolmap): a dataset folder for info and run"),
    ("synth", "a synthetic benchmark object with ground truth, rendered by Mitsuba 3"),
    ("geometry", "fit 3D Gaussians (3DGS with normals) to the photos: RUN/geometry/gaussians.ply"),
    ("predict", "per-view 2D material maps (base color, roughness, metallic) into RUN/materials2d/"),
    ("run", "the whole method: predict, geometry, lift, refine (finished stages are reused)"),
    ("relight", "render a run's asset under a new environment light (PNG frames, orbit MP4)"),
    ("view", "a browser viewer that relights the asset live under any light (viser)"),
    ("export", "the asset as a textured glTF 2.0 mesh (.glb) plus its environment map (.exr, .hdr)"),
    ("eval", "metrics against ground truth, the paper's tables and report.html"),
    ("demo", "make a benchmark object, run the method and its ablations, evaluate, write the report"),
    ("bench", "the demo over several objects, tables averaged"),
    ("batch", "the method once per object, as Ray tasks on this machine or a cluster; a summary over objects"),
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


RESUMING_COMMANDS = ("run", "geometry", "demo", "bench", "batch")  # staged: a rerun skips what is finished


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except MatsprayError as exc:
        print(f"matspray {args.command}: error: {flag_message(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if args.command in RESUMING_COMMANDS:
            print(
                f"matspray {args.command}: interrupted; finished stages are kept and a rerun resumes", file=sys.stderr
            )
        else:
            print(
                f"matspray {args.command}: interrupted; run it again to start over (no file is left half-written)",
                file=sys.stderr,
            )
        return 130


if __name__ == "__main__":
    sys.exit(main())
