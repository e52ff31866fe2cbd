"""`matspray predict --data DATA --out RUN --predictor SPEC`: per-view material maps into RUN/materials2d/."""

from pathlib import Path

SPLITS = ("train", "test", "all")


def add_predict_parser(parser) -> None:
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (Blender, TensoIR or COLMAP layout)")
    parser.add_argument("--out", type=Path, required=True, help="run folder; maps go to OUT/materials2d/")
    parser.add_argument(
        "--predictor",
        required=True,
        metavar="SPEC",
        help="files:DIR (precomputed maps: MatSpray, DiffusionRenderer or Marigold layout), marigold (diffusers, "
        "from --weights), simulated[:paper|harsh|outliers|dr] (an error model; "
        "plain simulated = paper) or ground-truth "
        "(benchmarks on `matspray synth` objects only)",
    )
    parser.add_argument(
        "--split", choices=SPLITS, default="train", help="views to predict (default: train, what lifting uses)"
    )
    parser.add_argument("--downscale", type=float, default=1.0, help="shrink images by this factor on load (default 1)")
    group = parser.add_argument_group("files and marigold")
    group.add_argument(
        "--basecolor-encoding",
        metavar="ENC",
        help="how stored base color relates to linear: srgb, gamma1.8 or linear "
        "(default: gamma1.8 for DiffusionRenderer output, srgb otherwise)",
    )
    group = parser.add_argument_group("marigold")
    group.add_argument(
        "--weights",
        help="MarigoldIntrinsicsPipeline folder, or a hub id when the network allows "
        "(default prs-eth/marigold-iid-appearance-v1-1)",
    )
    group.add_argument(
        "--normals-weights",
        help="MarigoldNormalsPipeline folder (or hub id, e.g. prs-eth/marigold-normals-v1-1): also predict normal "
        "maps (default: none)",
    )
    group.add_argument("--device", help="auto (default: CUDA when available), cpu, cuda or cuda:N")
    group.add_argument("--steps", type=int, help="denoising steps (default: the model's)")
    group.add_argument(
        "--ensemble-size", type=int, help="predictions per view; >= 3 also writes a confidence map (default 1)"
    )
    group.add_argument(
        "--processing-resolution", type=int, help="resolution the model works at (default: the model's; 0 = native)"
    )
    group = parser.add_argument_group("marigold and simulated")
    group.add_argument(
        "--batch-size", type=int, help="views per model call / window (default: marigold 4, simulated 8)"
    )
    group.add_argument(
        "--seed",
        type=int,
        help="random seed (default: marigold 0; simulated: the synth object's seed, 0 for other data)",
    )
    group = parser.add_argument_group("simulated")
    group.add_argument(
        "--severity", type=float, help="strength of the simulated failure modes; 0 = ground truth (default 1)"
    )


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
    options = PredictorOptions(
        basecolor_encoding=args.basecolor_encoding,
        weights=args.weights,
        normals_weights=args.normals_weights,
        device=args.device,
        steps=args.steps,
        ensemble_size=args.ensemble_size,
        processing_resolution=args.processing_resolution,
        batch_size=args.batch_size,
        seed=args.seed,
        severity=args.severity,
    )
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
