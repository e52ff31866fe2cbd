"""The `matspray` command: a thin layer over the library. Each subcommand NAME lives in a module of this package, alone
or beside the commands of its concern (`datasets`: info, colmap, synth; `batch`: demo, bench, batch), as
`add_NAME_parser(parser)` and `NAME_main(args) -> int`; heavy imports happen inside `NAME_main`."""

from __future__ import annotations

import argparse
import importlib
import sys

from matspray import __version__
from matspray.cli.options import flag_message
from matspray.errors import MatsprayError

# (command, its module under matspray.cli, one-line help); order is the order of `matspray --help`
COMMANDS = [
    ("info", "datasets", "describe a dataset folder and list every problem found"),
    ("colmap", "datasets", "structure from motion on a folder of photos (pycolmap): a dataset folder for info and run"),
    ("synth", "datasets", "a synthetic benchmark object with ground truth, rendered by Mitsuba 3"),
    ("geometry", "geometry", "fit 3D Gaussians (3DGS with normals) to the photos: RUN/geometry/gaussians.ply"),
    ("predict", "predict", "per-view 2D material maps (base color, roughness, metallic) into RUN/materials2d/"),
    ("run", "run", "the whole method: predict, geometry, lift, refine (finished stages are reused)"),
    ("relight", "relight", "render a run's asset under a new environment light (PNG frames, orbit MP4)"),
    ("view", "view", "a browser viewer that relights the asset live under any light (viser)"),
    ("export", "export", "the asset as a textured glTF 2.0 mesh (.glb) plus its environment map (.exr, .hdr)"),
    ("eval", "eval", "metrics against ground truth, the paper's tables and report.html"),
    ("demo", "batch", "make a benchmark object, run the method and its ablations, evaluate, write the report"),
    ("bench", "batch", "the demo over several objects, tables averaged"),
    ("batch", "batch", "the method once per object, as Ray tasks on this machine or a cluster; a summary over objects"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="matspray",
        description="MatSpray: turn multi-view photos of an object into a relightable 3D asset "
        "(3D Gaussians with base color, roughness, metallic, plus an environment light).",
    )
    parser.add_argument("--version", action="version", version=f"matspray {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name, summary in COMMANDS:
        module = importlib.import_module(f"matspray.cli.{module_name}")
        sub = subparsers.add_parser(name, help=summary, description=summary)
        getattr(module, f"add_{name}_parser")(sub)
        sub.set_defaults(_run=getattr(module, f"{name}_main"))
    return parser


RESUMING_COMMANDS = ("run", "geometry", "demo", "bench", "batch")  # staged: a rerun skips what is finished


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command is None:
        if unknown:
            parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        parser.print_help()
        return 2
    command = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
    if unknown:  # said by the command's own parser: its usage and its name, not the top level's
        command.error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return int(args._run(args) or 0)
    except MatsprayError as exc:
        print(f"matspray {args.command}: error: {flag_message(exc, args.command, command)}", file=sys.stderr)
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
