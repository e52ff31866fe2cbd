"""How much can fusing the per-view predictions gain at all? Ceilings on the generalisation protocol's objects.

    python -m benchmarks.ceilings [--set dev|eval] [--objects K] [--start I] [--models paper harsh outliers]
                                  [--preset demo|test] [--out DIR]

Reads the default runs that `python -m benchmarks.generalise` left in OUT (same --set, --preset, --out; run it
first) and scores, per object and error model, on the test views under the held-out lights:

  proj-average, full      the protocol's two assets (mean of the lifted per-view values; the Neural Merger)
  full, true light        `full` refined once more on the same lift with the object's true training light fixed (at the
                          learned light's size) instead of learning one (the pipeline's light probe; kept in
                          OBJECT/runs/MODEL-true-light): what estimating the light costs the merger
  full, true light, PA brightness  the same with its base colour scaled to proj-average's brightness (below): what is
                          left of that gain when the light may not set the brightness
  full, true base / rough / metal  `full` with only that channel group taken from the lifted truth (below): what each
                          of its materials still costs it
  full, truth's brightness  `full` with its base colour scaled per RGB channel to the lifted truth's mean: what its
                          overall brightness and tint cost (set by the predictions: a learned light trades them)
  softmax oracle          the lifted truth (below) clamped, per Gaussian and channel, to the range of the values
                          that Gaussian received from the predictor (`merger.clamp_to_seen_range`): the nearest a
                          softmax merger can get to the true materials (its relighting is not a strict bound: one
                          wrong value can offset another's error)
  ... base / rough / metal  proj-average with only that channel group taken from the softmax oracle: what fusing
                          that channel perfectly would gain on its own
  true base, PA brightness  proj-average with the lifted truth's base colour, scaled per RGB channel to proj-average's
                          mean over the Gaussians: the base colour a perfect fusion reaches when the overall brightness
                          and tint stay the predictions' (a learned light can trade them with the base colour, so
                          nothing in the photos sets them; a bias every view shares, like the tone curve, stays)
  lifted truth, PA brightness  the same for the whole lifted truth
  lifted truth            the true 2D maps lifted onto the same Gaussians with the same lift settings and averaged
                          (a perfect predictor; OBJECT/runs/ground-truth, the protocol's sanity-row run): lifted
                          truth - proj-average bounds what any fusion of better predictions could gain
  lifted truth, full's normals  the lifted truth shaded with `full`'s normals (refined with its materials) instead
                          of the geometry's: what the refinement's normals gain or cost
  lifted truth, true alpha  the lifted truth's G-buffer at each test view with its coverage alpha replaced by the
                          true mask: what the silhouette costs. The relighting figure composites every render with
                          the true mask, so alpha shows only where the Gaussians leave the object uncovered; there
                          the row has no materials or normals to shade (zeros), so it does not measure what filling
                          those holes would gain
  lifted truth, true normals  the lifted truth's rendered materials (and alpha) shaded with the true normals: what
                          the Gaussians' normals cost given those materials; the rest to the true G-buffer is the
                          lift's material blur (+ alpha)
  true maps, Gaussian normals  the true material maps shaded with the lifted truth's rendered normals, under the
                          true mask: what the Gaussians' normals alone cost (the true G-buffer minus this row)
  true G-buffer           the true maps and normals of each test view shaded by our renderer (the shading ceiling:
                          what the shading model alone costs against Mitsuba's path tracing)

The markdown splits the gap from the lifted truth to the true G-buffer over the rows between them.

`--configuration KEY` scores the runs `MODEL-KEY` of another configuration of `benchmarks.generalise` (the key its
log names), each with the truth lifted onto that run's own Gaussians (in `ground-truth-on-MODEL-KEY`): for
configurations that change the geometry, e.g. `--geometry predicted_normal_weight=1`. Its files get the suffix -KEY.
Among the default runs, those that trained their own geometry (their model's predicted normals are not the first
model's) get their own lifted truth the same way, in `ground-truth-on-MODEL`.

Writes OUT/ceilings-PRESET.json and .md (the models of earlier passes kept, this pass's replaced); each (object,
model)'s figures are kept in RUN/eval/ceilings.json and reused while no stage of the run changed, so an
interrupted pass resumes. `benchmarks.method --ceilings` uses
the same functions on the demo object.
"""

from __future__ import annotations

import argparse
import functools
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from benchmarks.ceilings_markdown import CHANNEL_GROUPS, FIGURES, GBUFFER_ROWS, ROWS, markdown
from benchmarks.generalise import (
    SET_SEEDS,
    add_part_arguments,
    check_part_arguments,
    object_config,
    objects_part,
    part_name,
    predictor_spec,
    print_lines,
    run_name,
    set_name,
)
from matspray.errors import ConfigError, RunError

CEILINGS_FILE = "ceilings.json"  # in RUN/eval/


# ------------------------------------------------------------------------------------------ ceilings of one run
def read_test_truth(data: Path) -> tuple[list, list, dict]:
    """The test views of `data`, their ground truth and the held-out lights (prefiltered), read once."""
    from matspray.data import load_scene
    from matspray.eval.run_eval import load_relight_lights, read_view_truth

    views = load_scene(data).test
    truths = [read_view_truth(v) for v in views]
    return views, truths, load_relight_lights(data, sorted(set.intersection(*(set(t.relit) for t in truths))))


def shading_ceiling(views: list, truths: list, lights: dict, shadows_from=None) -> dict:
    """Relighting metrics of the true G-buffer of every test view shaded by our renderer, per light;
    shadowed by the visibility of the asset `shadows_from` when given."""
    from matspray.data.images import read_raw
    from matspray.eval.evaluate import average_metrics, evaluate_images
    from matspray.eval.run_eval import unpremultiply
    from matspray.method.relight import render_gbuffer
    from matspray.render.shade.deferred import GBuffer, shade_gbuffer

    records = {name: [] for name in lights}
    for view, truth in zip(views, truths):
        normals = read_raw(view.path.with_name(f"{view.name}_normal.exr"))[..., :3]
        for name, light in lights.items():
            with torch.no_grad():
                shadow = None if shadows_from is None else render_gbuffer(shadows_from, view.camera, light).shadow
                gbuffer = GBuffer(truth.basecolor, truth.roughness, truth.metallic, normals, truth.mask, shadow)
                rgb = unpremultiply(shade_gbuffer(gbuffer, view.camera, light), truth.mask)
            records[name].append(evaluate_images(rgb, truth.relit[name], truth.mask))
    per_light = {name: average_metrics(r) for name, r in records.items()}
    return {"relighting": average_metrics([m for r in records.values() for m in r]), **per_light}


def require_same_lift(run: Path, config) -> None:
    """Refuse `run` unless it lifted with `config`'s lift settings (the truth must be lifted the same way)."""
    from matspray.rundir import RunDir, to_plain

    lifted, wanted = RunDir(run).config().get("lift"), to_plain(config.lift)
    if lifted != wanted:
        raise RunError(
            f"{run} lifted with other settings than these ({lifted} vs {wanted}); "
            "run it with the protocol's default settings"
        )


def lift_truth(data: Path, run: Path, truth_run: Path, config):
    """The ground-truth 2D maps lifted onto `run`'s Gaussians (its geometry shared into `truth_run`) and averaged:
    the proj-average asset of the ground-truth predictor. `run` must have lifted with `config` (checked first).
    Jobs for other error models of the same object share `truth_run`: they take turns, and the later ones reuse it."""
    from matspray.method.pipeline import Pipeline
    from matspray.method.plan import on_geometry
    from matspray.rundir import RunDir, share_stage

    require_same_lift(run, config)
    geometry = RunDir(run).stage_fingerprint("geometry")

    with RunDir(truth_run).hold(wait=True):  # another job lifting it goes first; this one then reuses its lift
        if RunDir(truth_run).stage_fingerprint("geometry") not in (None, geometry):
            raise RunError(f"{truth_run} holds another geometry than {run}; delete it to lift the truth again")
        share_stage(run, truth_run, "geometry")
        with Pipeline(
            data,
            truth_run,
            replace(config, predictor="ground-truth", predictor_options={}),
            progress=False,
            log=lambda _: None,
        ) as pipeline:
            # the truth goes onto `run`'s Gaussians whatever trained them (a geometry trained on an error model's
            # predicted normals has that model's predictions in its fingerprint, which the truth's plan lacks)
            pipeline.plan = on_geometry(pipeline.resolved(), geometry)
            return pipeline.run_all(("proj-average",))["proj-average"]


def softmax_reach(truth_materials: torch.Tensor, truth_run: Path, run: Path) -> torch.Tensor:  # [N, 5] -> [N, 5]
    """`truth_materials` clamped to the range of the per-view values `run`'s predictor gave each Gaussian."""
    from matspray.method.lift import load_lift
    from matspray.method.merger import clamp_to_seen_range

    truth, predicted = (
        load_lift(truth_run / "lift" / "projected.pt", "cpu"),
        load_lift(run / "lift" / "projected.pt", "cpu"),
    )
    if not torch.equal(truth.kept, predicted.kept):
        raise RunError(f"{truth_run} and {run} kept different Gaussians; delete {truth_run / 'lift'} and run again")
    return clamp_to_seen_range(truth_materials.cpu(), predicted.values, predicted.seen)


def with_groups(asset, source: torch.Tensor, groups):
    """`asset` with the channel `groups` (slices of the material layout) of its materials taken from `source` [N, 5]."""
    materials = asset.materials.clone()
    for group in groups:
        materials[:, group] = source[:, group].to(materials)
    return replace(asset, materials=materials)


def at_brightness(materials: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:  # [N, 5], [N, 5] -> [N, 5]
    """`materials` with its base colour scaled, per RGB channel, to the mean base colour of `reference`
    (over Gaussians)."""
    base = CHANNEL_GROUPS["base"]
    scaled = materials.clone()
    scaled[:, base] = (
        materials[:, base] * reference[:, base].mean(0) / materials[:, base].mean(0).clamp_min(1e-6)
    ).clamp(0.0, 1.0)
    return scaled


def summary_figures(summary: dict) -> dict:
    """relight / basecolor / roughness / metallic PSNR of an evaluation summary."""
    return {"relight": summary["relighting"]["psnr"], **{c: summary[c]["psnr"] for c in FIGURES[1:] if c in summary}}


def with_normals_of(asset, donor, donor_name: str):
    """`asset` with the normals of `donor`, an asset on the same Gaussians (the same geometry and lift)."""
    same = len(donor.gaussians) == len(asset.gaussians) and torch.allclose(
        donor.gaussians.means.cpu(), asset.gaussians.means.cpu(), atol=1e-6
    )
    if not same:  # another Gaussian's normal would shade each splat
        raise RunError(
            f"{donor_name} holds other Gaussians than the lifted truth ({len(donor.gaussians)} vs "
            f"{len(asset.gaussians)}): they must share the geometry and lift to swap normals"
        )
    return replace(asset, normals=donor.normals.to(asset.normals))


def gbuffer_row_figures(asset, views: list, truths: list, lights: dict, sources: tuple) -> dict:
    """Figures of `asset`'s G-buffer at every test view with the parts `sources` names "true" taken from the truth
    (`GBUFFER_ROWS`; `benchmarks.ceiling_gbuffers`). A row with the true maps has only its relighting: its material
    figures would score the truth against itself."""
    from benchmarks.ceiling_gbuffers import gbuffer_row_summary

    figures = summary_figures(gbuffer_row_summary(asset, views, truths, lights, sources))
    return figures if sources[0] == "asset" else {"relight": figures["relight"]}


@dataclass(frozen=True)
class ObjectTruth:
    """What every error model of one object is scored against, computed once per object."""

    views: list  # the test views
    truths: list  # their ground truth
    lights: dict  # the held-out lights, prefiltered
    asset: object  # the lifted truth (an Asset)
    run: Path  # the run folder it was lifted in
    gbuffer_relight: float  # relighting PSNR of the true G-buffer (the shading ceiling)


def object_truth(data: Path, run: Path, truth_run: Path, config) -> ObjectTruth:
    """The test views, the truth lifted onto `run`'s Gaussians in `truth_run`, and the shading ceiling."""
    views, truths, lights = read_test_truth(data)
    asset = lift_truth(data, run, truth_run, config)
    return ObjectTruth(
        views, truths, lights, asset, truth_run, shading_ceiling(views, truths, lights)["relighting"]["psnr"]
    )


def refine_under_true_light(data: Path, run: Path, folder: Path, config):
    """`run`'s `full` refined again in `folder` with the object's true training light as its light probe (the
    pipeline's `light_probe`, at the size of the light `config` learns); its predictions, geometry and lift are shared
    from `run`, which must have made them with `config`. Reused while the refinement's fingerprint holds."""
    from matspray.eval.light import training_light_path
    from matspray.method.pipeline import Pipeline
    from matspray.rundir import RunDir, share_stage

    probe = training_light_path(data)
    if probe is None:
        raise RunError(f"{data}: no scene.json naming the training light (a `matspray synth` object has one)")
    for stage in ("materials2d", "geometry", "lift"):
        share_stage(run, folder, stage)
    pipeline = Pipeline(data, folder, replace(config, light_probe=str(probe)), progress=False, log=lambda _: None)
    made = RunDir(run)
    if (pipeline.plan.predict.fingerprint, pipeline.resolved().lift.fingerprint) != (
        made.stage_fingerprint("materials2d"),
        made.stage_fingerprint("lift"),
    ):
        raise RunError(f"{run} predicted or lifted with other settings than the protocol's defaults; run it with those")
    return pipeline.refine("full")


def run_ceilings(run: Path, truth, under_true_light, rows=ROWS) -> dict:
    """{row: figures} of `rows` for one run folder with `proj-average` and `full` assets (see the module's docstring).
    `truth()`: its ObjectTruth (the test views and what they are scored against); `under_true_light()`: its `full`
    refined under the true light (called only when a row needs it)."""
    from matspray.eval.run_eval import evaluate_asset
    from matspray.method.asset import read_asset
    from matspray.presets import asset_stage

    averaged, full = (read_asset(run / asset_stage(v)) for v in ("proj-average", "full"))
    t = truth()
    under_true_light = functools.cache(under_true_light)

    @functools.cache
    def reach():  # the lifts are read once, whichever rows need them
        return softmax_reach(t.asset.materials, t.run, run)

    def true_materials():
        return t.asset.materials.to(averaged.materials)

    assets = {
        "proj-average": lambda: averaged,
        "full": lambda: full,
        "full, true light": under_true_light,
        "full, true light, PA brightness": lambda: replace(
            under_true_light(), materials=at_brightness(under_true_light().materials, averaged.materials)
        ),
        **{
            f"full, true {name}": functools.partial(lambda g: with_groups(full, true_materials(), [g]), group)
            for name, group in CHANNEL_GROUPS.items()
        },
        "full, truth's brightness": lambda: replace(full, materials=at_brightness(full.materials, true_materials())),
        "softmax oracle": lambda: with_groups(averaged, reach(), CHANNEL_GROUPS.values()),
        **{
            f"oracle {name} only": functools.partial(lambda g: with_groups(averaged, reach(), [g]), group)
            for name, group in CHANNEL_GROUPS.items()
        },
        "true base, PA brightness": lambda: with_groups(
            averaged, at_brightness(true_materials(), averaged.materials), [CHANNEL_GROUPS["base"]]
        ),
        "lifted truth, PA brightness": lambda: replace(
            averaged, materials=at_brightness(true_materials(), averaged.materials)
        ),
        "lifted truth": lambda: replace(averaged, materials=true_materials()),
        "lifted truth, full's normals": lambda: with_normals_of(assets["lifted truth"](), full, str(run / "asset")),
    }

    def figures(row: str) -> dict:
        if row == "true G-buffer":
            return {"relight": t.gbuffer_relight}
        if row in GBUFFER_ROWS:  # the lifted truth's G-buffer, partly swapped for the truth
            return gbuffer_row_figures(assets["lifted truth"](), t.views, t.truths, t.lights, GBUFFER_ROWS[row])
        return summary_figures(evaluate_asset(assets[row](), t.views, t.truths, t.lights, None)["summary"])

    return {row: figures(row) for row in rows}


# ------------------------------------------------------------------------------------------ the protocol's objects
def cached_ceilings(run: Path, truth_run: Path, truth, under_true_light, rows=ROWS) -> dict:
    """`run_ceilings(run, truth, under_true_light, rows)`; the rows already in RUN/eval/ceilings.json are reused while
    no stage of either run folder is newer than it, so only missing rows (e.g. ones a newer version adds) are
    computed; the file keeps every row computed so far."""
    from matspray.rundir import newer_than_stages, read_json, write_json

    path = run / "eval" / CEILINGS_FILE
    kept = read_json(path) if newer_than_stages(path, run, truth_run) else {}
    missing = [row for row in rows if row not in kept]
    if missing:
        kept |= run_ceilings(run, truth, under_true_light, missing)
        write_json(path, {row: kept[row] for row in ROWS if row in kept})
    return {row: kept[row] for row in ROWS if row in rows}


def merge_with_saved(path: Path, results: dict, log=print) -> dict:
    """Writes `results` ({model: [per-object figures]}) to `path`, keeping the models of earlier passes that this pass
    did not run; returns what was written. Call it holding `held_exclusively(path)`."""
    from matspray.rundir import read_json, write_json

    kept = {}
    for model, per_object in (read_json(path) if path.exists() else {}).items():
        if model in results:
            continue
        if all(list(o["rows"]) == list(ROWS) for o in per_object):
            kept[model] = per_object
        else:  # saved by a version with other rows: its runs' saved figures gain the new rows on the next pass
            # over them
            log(
                f"ceilings: error model {model} in {path} has other rows (an older version); dropped: "
                f"pass --models {model} to add it again"
            )
    write_json(path, kept | results)  # the models of earlier passes stay, this pass's replace theirs
    return kept | results


def truth_run_name(run: Path, first: Path, key: str | None) -> str:
    """The run folder, beside `run`, that holds the truth lifted onto `run`'s Gaussians. `ground-truth` (the
    protocol's sanity-row run) serves the default runs of one geometry: the one it already holds, or else the one
    the pass's first run (`first`) will lift it onto. A default run with another geometry (its model's predicted
    normals differ) and another configuration's runs each get their own, `ground-truth-on-RUN`."""
    from matspray.rundir import RunDir

    if key is None:
        held = RunDir(run.parent / run_name("ground-truth", None)).stage_fingerprint("geometry")
        if (held or RunDir(first).stage_fingerprint("geometry")) == RunDir(run).stage_fingerprint("geometry"):
            return run_name("ground-truth", None)
    return f"ground-truth-on-{run.name}"


def run_set(args, log=print) -> list[str]:
    from matspray.method.config import build_config
    from matspray.render.shade.lights import hdri_files
    from matspray.rundir import held_exclusively, write_text_atomic

    objects = objects_part(args.set, args.start, args.objects, sorted(hdri_files()))
    config = build_config(args.preset)  # the protocol's default settings (lift included), whatever the predictor
    results = {model: [] for model in args.models}
    key = args.configuration
    for number, spec in enumerate(objects, 1):
        folder = args.out / "objects" / spec.name
        run_dirs = {model: folder / "runs" / run_name(model, key) for model in args.models}
        first = run_dirs[args.models[0]]
        truth_runs = {model: folder / "runs" / truth_run_name(run, first, key) for model, run in run_dirs.items()}
        truths = {}  # per truth run its lifted truth, made once for the runs that share it (they share one geometry)
        for model, run_dir in run_dirs.items():
            truth_run = truth_runs[model]
            truth = truths.setdefault(
                truth_run, functools.cache(functools.partial(object_truth, folder / "data", run_dir, truth_run, config))
            )
            model_config = object_config(replace(config, predictor=predictor_spec(model)), spec)
            under_true_light = functools.partial(
                refine_under_true_light,
                folder / "data",
                run_dir,
                folder / "runs" / f"{run_dir.name}-true-light",
                model_config,
            )
            if not all((run_dir / stage / "stage.json").exists() for stage in ("asset", "asset-proj-average", "lift")):
                raise ConfigError(
                    f"{run_dir}: no finished full and proj-average assets; "
                    f"run `python -m benchmarks.generalise --set {args.set} "
                    f"--objects {args.start + len(objects)} --models {model} --preset {args.preset} "
                    f"--out {args.out}` first"
                )
            require_same_lift(run_dir, config)
            log(f"ceilings: object {number}/{len(objects)} {spec.name}, error model {model}")
            results[model].append(
                {"object": spec.name, "rows": cached_ceilings(run_dir, truth_run, truth, under_true_light, args.rows)}
            )
    suffix = "" if key is None else f"-{key}"
    path = args.out / f"ceilings-{part_name(args.preset, args.start)}{suffix}.json"
    with held_exclusively(
        path
    ):  # jobs for other error models may finish at the same time: each keeps the others' models
        saved = merge_with_saved(path, results, log)
        write_text_atomic(path.with_suffix(".md"), "\n".join(markdown(args.set, args.preset, saved)) + "\n")
    return markdown(args.set, args.preset, results)


def parse_args(argv=None):
    from matspray.predictors.error_models import ERROR_MODELS

    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.ceilings", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--set", type=set_name, choices=tuple(SET_SEEDS), default="dev", help="the protocol's object set (default dev)"
    )
    add_part_arguments(parser)
    parser.add_argument(
        "--models",
        nargs="+",
        default=list(ERROR_MODELS),
        choices=ERROR_MODELS,
        metavar="MODEL",
        help=f"error models (default: {' '.join(ERROR_MODELS)})",
    )
    parser.add_argument("--preset", choices=("test", "demo"), default="demo")
    parser.add_argument("--out", type=Path, help="the protocol's folder (default runs/generalise-SET-PRESET)")
    parser.add_argument(
        "--rows",
        nargs="+",
        default=list(ROWS),
        choices=ROWS,
        metavar="ROW",
        help="only these rows (default: all; the 'full, true light' rows refine once more per run)",
    )
    parser.add_argument(
        "--configuration",
        metavar="KEY",
        help="score the runs MODEL-KEY of this benchmarks.generalise configuration instead of the default runs",
    )
    args = parser.parse_args(argv)
    check_part_arguments(parser, args)
    if args.configuration and any(row.startswith("full, true light") for row in args.rows):
        parser.error("--configuration: the 'full, true light' rows refine the default runs only; leave them out")
    args.out = args.out or Path("runs") / f"generalise-{args.set}-{args.preset}"
    return args


def main(argv=None) -> int:
    return print_lines(run_set, parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
