"""`matspray bench --objects N` or `--assets PATH...`: the method on several benchmark objects, tables averaged."""

from pathlib import Path

from matspray.cli.options import add_method_arguments, build_config_from_args


def add_parser(parser) -> None:
    parser.add_argument("--objects", type=int, default=None, help="number of procedural objects (shapes in turn, seeds 0..N-1; default 3)")
    parser.add_argument("--assets", nargs="+", type=Path, default=None, metavar="PATH",
                        help="glTF 2.0 files (.glb/.gltf) or folders of them: one benchmark object each (`synth --asset`), "
                             "instead of procedural ones")
    parser.add_argument("--out", type=Path, help="folder for everything (default: runs/bench-PRESET, with --assets runs/bench-assets-PRESET)")
    add_method_arguments(parser)


def run(args) -> int:
    from matspray.demo import asset_objects, check_assets, run_bench
    from matspray.errors import ConfigError

    if args.assets is not None and args.objects is not None:
        raise ConfigError("--objects and --assets exclude each other; give one")
    objects = asset_objects(args.assets) if args.assets is not None else (3 if args.objects is None else args.objects)
    if args.assets is not None:
        check_assets(objects)
    out = args.out or Path("runs") / (f"bench-assets-{args.preset}" if args.assets is not None else f"bench-{args.preset}")
    run_bench(out, objects, preset=args.preset, config=build_config_from_args(args, predictor="simulated"))
    print(f"averaged tables: {out / 'tables.md'}")
    return 0
