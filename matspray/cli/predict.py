"""`matspray predict --data DATA --out RUN --predictor SPEC`: per-view material maps into RUN/materials2d/."""

from pathlib import Path

from matspray.cli.options import output_folder

SPLITS = ("train", "test", "all")


def add_predict_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=output_folder, required=True, help="run folder; maps go to OUT/materials2d/")
    from matspray.predictors.kinds import add_option_flags, predictor_usage

    parser.add_argument("--predictor", required=True, metavar="SPEC", help=predictor_usage())
    parser.add_argument(
        "--split", choices=SPLITS, default="train", help="views to predict (default: train, what lifting uses)"
    )
    parser.add_argument("--downscale", type=float, default=1.0, help="shrink images by this factor on load (default 1)")
    add_option_flags(parser)  # each predictor's options (`matspray.predictors.kinds`)


def predict_main(args) -> int:
    from matspray import __version__
    from matspray.data import load_scene
    from matspray.errors import DataError
    from matspray.predictors import (
        PredictorOptions,
        make_predictor,
        options_for_dataset,
        predict_views,
        write_materials2d,
    )
    from matspray.predictors.kinds import options_from_args
    from matspray.rundir import RunDir

    check_run_split(args.out, args.split)
    scene = load_scene(args.data, downscale=args.downscale)
    views = scene.views if args.split == "all" else scene.split(args.split)
    if not views:
        raise DataError(f"{args.data}: the {args.split} split has no views")
    shared = sorted({v.name for v in scene.train} & {v.name for v in scene.test})
    if args.split == "all" and shared:
        raise DataError(
            f"{args.data}: train and test views share names ({', '.join(shared[:5])}), "
            "and maps are stored by view name; "
            "predict one split at a time (--split train, or --split test into another --out)"
        )
    options = PredictorOptions(**options_from_args(args))
    predictor = make_predictor(args.predictor, options_for_dataset(args.predictor, options, args.data))
    with RunDir(args.out).hold():  # refused while another process writes the run folder, before predicting anything
        maps = predict_views(views, predictor)
        info = dict(
            predictor.describe(),  # after predicting: a simulated predictor describes the errors it drew
            spec=args.predictor,
            data=str(args.data),
            split=args.split,
            downscale=args.downscale,
            matspray_version=__version__,
        )
        replacing = (args.out / "materials2d").exists()
        folder = write_materials2d(args.out, maps, info)
    if replacing:
        print(f"replaced the previous maps in {folder}")
    label = "SIMULATED maps" if predictor.simulated else "maps"
    print(f"wrote {label} of {len(maps)} {args.split} view(s) from the {predictor.name} predictor to {folder}")
    return 0


def check_run_split(run_dir: Path, split: str) -> None:
    """Refuse to replace the maps of one split with those of another (lifting needs the train maps)."""
    from matspray.errors import RunError
    from matspray.predictors import read_predictor_info

    if not (run_dir / "materials2d" / "predictor.json").exists():
        return
    previous = read_predictor_info(run_dir).get("split")
    if previous is not None and previous != split:
        raise RunError(
            f"{run_dir / 'materials2d'}: holds maps of the {previous} split; "
            f"predicting the {split} split would replace them "
            f"(use another --out, e.g. for evaluation predictions, or delete that folder first)"
        )
