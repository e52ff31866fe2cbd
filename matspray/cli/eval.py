"""`matspray eval --run RUN [--data DATA]`: metrics, the paper's tables and the HTML report.
`matspray eval --glb FILE.glb [--data DATA]`: the same for a mesh made by `matspray export`."""

from pathlib import Path

from matspray.cli.options import add_compute_arguments, given, hidden_alias, refuse
from matspray.errors import ConfigError

CAPTURE_LIGHTS = ["studio", "sunset", "forest"]  # --env's default
GLB_ONLY = ("--frame", "--spp")  # flags that only `eval --glb` reads
CAPTURE_ONLY = ("--env", "--credit", "--compare")  # flags that only a capture's report reads


def add_eval_parser(parser) -> None:
    parser.add_argument(
        "--run",
        type=Path,
        help="run folder made by `matspray run` (with --glb: the run whose Gaussian asset to compare with; "
        "default: the run the file was exported from)",
    )
    parser.add_argument(
        "--glb",
        type=Path,
        help="evaluate this mesh from `matspray export` instead: Mitsuba renders it under the held-out "
        "lights at the test cameras; metrics, tables and report.html go to FILE_eval/ beside it",
    )
    parser.add_argument(
        "--frame",
        choices=("gltf", "dataset"),
        help="with --glb: the frame the file is in (default: what its extras say)",
    )
    parser.add_argument(
        "--spp", type=int, help="with --glb: Mitsuba samples per pixel (default: as the dataset's truth)"
    )
    parser.add_argument("--data", type=Path, help="the run's dataset (default: the folder the run was made from)")
    parser.add_argument(
        "--lpips-weights",
        type=Path,
        help="LPIPS v0.1 AlexNet weights, one .npz (the offline path); default: $MATSPRAY_LPIPS_WEIGHTS, else "
        "torchvision's AlexNet in torch's cache (python -m matspray.eval.lpips --download), else LPIPS is n/a",
    )
    parser.add_argument(
        "--aligned", action="store_true", help="also report base color and relighting after per-channel scale alignment"
    )
    parser.add_argument("--no-report", action="store_true", help="skip report.html")
    parser.add_argument(
        "--credit", help="a run on a capture without ground truth: a line crediting the photos, shown in its report"
    )
    parser.add_argument(
        "--env",
        nargs="+",
        metavar="NAME|PATH",
        help=(
            "a run on a capture without ground truth: lights its report shows the asset under, names "
            "(`matspray relight --help`) or .exr/.hdr files (default: " + " ".join(CAPTURE_LIGHTS) + ")"
        ),
    )
    parser.add_argument(
        "--compare",
        nargs="+",
        type=Path,
        default=[],
        metavar="RUN",
        help=(
            "a run on a capture without ground truth: other runs of the same capture (say, before a change of "
            "settings) whose assets its report shows beside this one's, relit under the first --env light and cut "
            "to the same square around the object"
        ),
    )
    hidden_alias(parser, "--relight", "env", nargs="+")  # the old name of --env
    add_compute_arguments(parser)


def refuse_unread_flags(args) -> None:
    """The flags that this kind of evaluation would not read (the dataset's kind is checked once it is loaded)."""
    if args.glb is None:
        refuse(given(args, GLB_ONLY), "for --glb (the evaluation of an exported mesh)")
    else:
        refuse(given(args, CAPTURE_ONLY + ("--aligned",)), "for --run, not --glb")
    if args.no_report:
        refuse(given(args, CAPTURE_ONLY), "for a capture's report, which --no-report leaves out")


def eval_main(args) -> int:
    from matspray.device import out_of_memory_as_error
    from matspray.render.backend import compute_target

    refuse_unread_flags(args)
    device, backend = compute_target(args.device, args.backend)
    if args.glb is not None:
        from matspray.eval.glb import evaluate_glb

        with out_of_memory_as_error("eval", device):
            evaluate_glb(
                args.glb,
                args.data,
                run=args.run,
                frame=args.frame,
                lpips_weights=args.lpips_weights,
                spp=args.spp,
                device=device,
                backend=backend,
            )
        out = args.glb.with_name(f"{args.glb.stem}_eval")
        print((out / "tables.md").read_text())
        print(f"report: {out / 'report.html'}")
        return 0
    if args.run is None:
        raise ConfigError("give --run RUN (a run to evaluate) or --glb FILE.glb (an exported mesh)")
    from matspray.data import load_run_scene
    from matspray.eval.heldout import evaluate_capture, has_ground_truth, heldout_table
    from matspray.eval.report import write_report
    from matspray.eval.run_eval import evaluate_run
    from matspray.rundir import RunDir

    run_folder = RunDir(args.run).require()
    scene = load_run_scene(run_folder, args.data)
    if has_ground_truth(scene):
        refuse(given(args, CAPTURE_ONLY), "for runs on a capture without ground truth; this dataset has it")
    else:  # a real capture: its held-out photos are the only truth
        from matspray.eval.capture_report import comparable_runs, write_capture_report
        from matspray.render.shade.lights import load_envmap

        refuse(given(args, ("--aligned",)), "for datasets with ground truth (a capture's photos need no alignment)")
        comparable_runs(run_folder, args.compare)  # a wrong --compare is refused before the work
        lights = args.env or CAPTURE_LIGHTS
        for light in lights:  # and a wrong --env
            load_envmap(light, height=16)
        print("eval: the dataset has no ground-truth materials (a real capture): scoring the held-out photos instead")
        with out_of_memory_as_error("eval", device):
            metrics = evaluate_capture(
                args.run, lpips_weights=args.lpips_weights, device=device, backend=backend, scene=scene
            )
            print(heldout_table(metrics))
            if not args.no_report:
                page = write_capture_report(
                    args.run,
                    metrics,
                    lights,
                    args.credit,
                    device=device,
                    backend=backend,
                    compare=args.compare,
                )
                print(f"report: {page}")
        return 0
    with out_of_memory_as_error("eval", device):
        metrics = evaluate_run(
            args.run,
            args.data,
            lpips_weights=args.lpips_weights,
            aligned=args.aligned,
            device=device,
            backend=backend,
            scene=scene,
        )
    print((args.run / "eval" / "tables.md").read_text())
    if not args.no_report:
        print(f"report: {write_report(args.run, metrics, args.data)}")
    return 0
