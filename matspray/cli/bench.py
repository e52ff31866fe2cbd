"""`matspray bench --objects N` or `--assets PATH...`: the method on several benchmark objects (through
`matspray batch`), tables averaged."""

import sys
from pathlib import Path

from matspray.cli.options import COMPUTE_FLAGS, add_method_arguments, build_config_from_args
from matspray.cli.settings import add_set_argument


def add_parser(parser) -> None:
    parser.add_argument(
        "--objects",
        type=int,
        default=None,
        help="number of procedural objects (shapes in turn, seeds 0..N-1; default 3)",
    )
    parser.add_argument(
        "--assets",
        nargs="+",
        type=Path,
        default=None,
        metavar="PATH",
        help="glTF 2.0 files (.glb/.gltf) or folders of them: one benchmark object each (`synth --asset`), "
        "instead of procedural ones",
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="folder for everything (default: runs/bench-PRESET, with --assets runs/bench-assets-PRESET)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        help="objects at once, as Ray tasks (default: one per CPU core; without Ray installed, one after another)",
    )
    add_method_arguments(parser, visible=COMPUTE_FLAGS)
    add_set_argument(parser)


def run(args) -> int:
    from matspray.batch.demo import asset_objects, check_assets, run_bench
    from matspray.errors import ConfigError

    if args.assets is not None and args.objects is not None:
        raise ConfigError("--objects and --assets exclude each other; give one")
    objects = asset_objects(args.assets) if args.assets is not None else (3 if args.objects is None else args.objects)
    if args.assets is not None:
        check_assets(objects)
    out = args.out or Path("runs") / (
        f"bench-assets-{args.preset}" if args.assets is not None else f"bench-{args.preset}"
    )
    summary = run_bench(
        out,
        objects,
        preset=args.preset,
        config=build_config_from_args(args, predictor="simulated"),
        workers=args.workers,
    )
    for failure in summary["failed"]:
        print(f"failed: {failure['name']}: {failure['error']}", file=sys.stderr)
    if summary["averages"] is not None:
        print(f"averaged tables: {out / 'tables.md'}")
    print(f"per object: {out / 'summary.md'}")
    return 1 if summary["failed"] else 0
