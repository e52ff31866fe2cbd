"""Do predicted normal maps help refinement? The protocol's objects refined with the predictor's normals as a target.

    python -m benchmarks.normal_targets [--set dev|eval] [--objects K] [--start I] [--models dr ...]
                                        [--weights 1.0 ...] [--preset demo|test] [--out DIR]

Reads the default runs that `python -m benchmarks.generalise` left in OUT (same --set, --preset, --out; run it first)
and, per object, error model and weight W, refines `full` in OBJECT/runs/MODEL-normals-W: the default run's geometry
and lift are shared (hard links), the 2D maps are predicted again so that they carry the simulated normal maps (runs
predicted before normal maps were kept have none; the materials are drawn the same, so the lift is reused), and
`refine.predicted_normal_weight` is W. Prints, per object, the relighting PSNR under the held-out lights and the mean
angle of the rendered normals to the true ones on the test views, beside the default run's `full` and `proj-average`
(the geometry's normals). Each refined run is reused while its fingerprints hold.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from benchmarks.generalise import (
    SET_SEEDS,
    add_part_arguments,
    check_part_arguments,
    object_config,
    objects_part,
    predictor_spec,
    print_lines,
    run_name,
)
from benchmarks.generalise_tables import fmt
from matspray.errors import ConfigError


def scored(asset, truth) -> dict:
    """Relighting PSNR and the normals' mean angular error (degrees) of `asset` on the object's test views."""
    from matspray.eval.run_eval import evaluate_asset

    summary = evaluate_asset(asset, truth[0], truth[1], truth[2], None)["summary"]
    return {"relight": summary["relighting"]["psnr"], "normals_deg": summary.get("normals", {}).get("error_deg")}


def refined_with_normals(data: Path, default_run: Path, folder: Path, config):
    """`full` refined in `folder` with the default run's geometry and lift, predicted normals weighted as `config`
    says."""
    from matspray.method.pipeline import Pipeline
    from matspray.rundir import share_stage

    for stage in ("geometry", "lift"):
        share_stage(default_run, folder, stage)
    with Pipeline(data, folder, config, progress=False, log=lambda _: None) as pipeline:
        if pipeline.resolved().lift.fingerprint != _stage_fingerprint(default_run, "lift"):
            raise ConfigError(f"{default_run} lifted with other settings than the protocol's defaults; rerun it")
        return pipeline.refine("full")


def _stage_fingerprint(run: Path, stage: str) -> str:
    from matspray.rundir import RunDir

    return RunDir(run).stage_fingerprint(stage)


def run_objects(args, log=print) -> list[str]:
    from benchmarks.ceilings import read_test_truth
    from matspray.method.asset import read_asset
    from matspray.method.config import build_config
    from matspray.render.shade.lights import hdri_files

    objects = objects_part(args.set, args.start, args.objects, sorted(hdri_files()))
    config = build_config(args.preset)
    head = ["object", "model", "full", "proj-average"] + [f"predicted normals x{w:g}" for w in args.weights]
    lines = [
        f"Relighting PSNR (dB) / normals' mean angle to the truth (deg), {args.set} set, preset {args.preset}",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for spec in objects:
        folder = args.out / "objects" / spec.name
        for model in args.models:
            default_run = folder / "runs" / run_name(model, None)
            if not all((default_run / stage / "stage.json").exists() for stage in ("asset", "asset-proj-average")):
                raise ConfigError(
                    f"{default_run}: no finished full and proj-average assets; run `python -m benchmarks.generalise "
                    f"--set {args.set} --objects {args.start + len(objects)} --models {model} --preset {args.preset} "
                    f"--out {args.out}` first"
                )
        truth = read_test_truth(folder / "data")
        for model in args.models:
            default_run = folder / "runs" / run_name(model, None)
            cells = [scored(read_asset(default_run / stage), truth) for stage in ("asset", "asset-proj-average")]
            for weight in args.weights:
                log(f"normal targets: {spec.name}, {model}, weight {weight:g}")
                model_config = object_config(replace(config, predictor=predictor_spec(model)), spec)
                model_config = replace(
                    model_config, refine=replace(model_config.refine, predicted_normal_weight=weight)
                )
                run = folder / "runs" / run_name(model, f"normals-{weight:g}")
                cells.append(scored(refined_with_normals(folder / "data", default_run, run, model_config), truth))
            lines.append(
                f"| {spec.name} | {model} | "
                + " | ".join(f"{fmt(c['relight'])} / {fmt(c['normals_deg'])}" for c in cells)
                + " |"
            )
    return lines


def parse_args(argv=None):
    from matspray.predictors.error_models import ERROR_MODELS

    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.normal_targets",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--set", choices=tuple(SET_SEEDS), default="dev", help="the protocol's object set (default dev)"
    )
    add_part_arguments(parser)
    parser.add_argument("--models", nargs="+", default=["dr"], choices=ERROR_MODELS, metavar="MODEL")
    parser.add_argument("--weights", nargs="+", type=float, default=[1.0], help="predicted_normal_weight values")
    parser.add_argument("--preset", choices=("test", "demo"), default="demo")
    parser.add_argument("--out", type=Path, help="the protocol's folder (default runs/generalise-SET-PRESET)")
    args = parser.parse_args(argv)
    check_part_arguments(parser, args)
    if not all(w > 0 for w in args.weights):
        parser.error("--weights: every weight must be > 0")
    args.out = args.out or Path("runs") / f"generalise-{args.set}-{args.preset}"
    return args


def main(argv=None) -> int:
    return print_lines(run_objects, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
