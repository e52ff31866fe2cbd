"""Does the method beat its baselines on objects it was never tuned on? The benchmark protocol.

    python -m benchmarks.generalise --set dev|dev-b|real-dev|real-eval [--objects K] [--start I] [--preset demo|test]
        [--models paper harsh outliers dr ground-truth] [--variants full proj-average supervised no-softmax]
        [--method matspray|paper] [--without ADDITION ...] [setting flags of `matspray run`]
        [--refine KEY=VALUE ...] [--tag NAME] [--out DIR]
    python -m benchmarks.generalise --set dev --compare [--out DIR]

Two procedural development sets with disjoint seeds: `dev` (seeds 1000 + i) and `dev-b` (seeds 2000 + i; once the
evaluation set, it was used to choose defaults and is development now). Object i is a procedural `random` shape (the
seed picks it), trained under one HDRI of ../shared/data/hdri and relit under two other lights (HDRIs and built-ins),
all drawn from its seed. The real sets
`real-dev` (3 objects, seeds 3000 + i) and `real-eval` (5 objects, seeds 4000 + i, run once on final defaults) are
artist-made glTF objects kept in benchmarks/real (benchmarks/real_objects.py names them and their split), rendered
by `matspray synth --asset` and lit the same way. Each object is run with every predictor error model
(`simulated:paper`, `:harsh`, `:outliers`, `:dr`, and the ground truth as a sanity row; a simulated predictor draws
its errors from the object's seed): one run folder per (object, model, configuration). Each run trains its Gaussian
Splatting on its model's predicted normals (`geometry.predicted_normal_weight`, on by default); with that weight at
0 the geometry is trained once per object and shared by hard links (the pipeline's stage fingerprint checks it is
the same). A configuration other than the default also starts from the default run's predictions, geometry, lift and
shadows, which its pipeline keeps when its settings leave them unchanged and redoes otherwise. Every variant is
refined, evaluated against the ground truth, and the raw 2D predictions of the test views are scored as the baseline
3D must beat.

Prints, per error model, a table per object and the mean over objects (relighting PSNR of every variant;
base colour, roughness, metallic PSNR of the full method's 3D materials and of the 2D predictions;
metallic means follow the paper's infinity rule), the wins out of N (full vs proj-average, full vs
no-softmax, 3D vs 2D per channel) and the seconds per object. Writes OUT/results-TAG.json and .md, and
per model OUT/tables-TAG-MODEL.md (the paper's tables averaged over the objects).
`--refine KEY=VALUE` overrides a refinement setting (RefineConfig field; `merger.KEY` for the merger)
for development sweeps: earlier stages are reused, so a sweep costs only refinement and evaluation.
`--geometry KEY=VALUE` overrides a geometry setting (GeometryConfig field), e.g. `predicted_normal_weight=0` for
one geometry per object, shared by its models.
Each configuration keeps its results file (its --tag), and `--compare` prints one row per configuration
and error model from them: the development-set table of choices.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

from benchmarks.generalise_sets import (  # noqa: F401  (object_set, SET_SEEDS: read by the tests and benchmarks)
    DEFAULT_OBJECTS,
    EVAL_SETS,
    REAL_SETS,
    SET_SEEDS,
    ObjectSpec,
    object_set,
    objects_part,
    set_name,
    with_training_light,
)
from benchmarks.generalise_tables import choices_table, markdown, model_summary, object_figures
from benchmarks.real_objects import REPO_ROOT
from matspray.batch.demo import DEMO_SIZES, make_demo_object, run_object
from matspray.cli.options import add_method_arguments, build_config_from_args, flag_message, method_settings_from_args
from matspray.cli.settings import add_set_argument, settings_from_overrides
from matspray.errors import ConfigError, MatsprayError
from matspray.eval.run_eval import paper_tables
from matspray.eval.tables import write_tables
from matspray.geometry.config import GeometryConfig
from matspray.method.config import default_settings
from matspray.method.pipeline import Pipeline
from matspray.predictors.error_models import ERROR_MODELS
from matspray.presets import METHODS
from matspray.presets import VARIANT_NAMES as VARIANTS
from matspray.render.shade.lights import hdri_files
from matspray.rundir import (
    STAGE_RECORD,
    RunDir,
    fingerprint,
    held_exclusively,
    newer_than_stages,
    read_json,
    share_stage,
    write_json,
    write_text_atomic,
)

MODELS = (*ERROR_MODELS, "ground-truth")


def part_name(name: str, start: int) -> str:
    """The name of a part's files: a pass split over jobs keeps each part's files apart from the whole pass's."""
    return name if start == 0 else f"{name}-from{start}"


def add_part_arguments(parser) -> None:
    parser.add_argument(
        "--objects",
        type=int,
        default=None,
        help=f"objects of the set, the first K (default {DEFAULT_OBJECTS}; of a real set, all of them)",
    )
    parser.add_argument(
        "--start",
        type=int,
        default=0,
        help="skip the set's first I objects, to split a pass over jobs that run at once "
        "(a part's files get the suffix -fromI; a later pass over all objects reuses every finished run)",
    )


def print_lines(lines_of, args) -> int:
    """A protocol benchmark's `main` after parsing: print the lines `lines_of(args)` returns, or a MatsprayError in
    one line (exit 2)."""
    try:
        lines = lines_of(args)
    except MatsprayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("\n" + "\n".join(lines))
    return 0


def check_part_arguments(parser, args) -> None:
    if args.start < 0 or args.objects is not None and args.objects < 1:
        parser.error(f"--objects must be >= 1 and --start >= 0 (got {args.objects} and {args.start})")


def predictor_spec(model: str) -> str:
    if model not in MODELS:
        raise ConfigError(f"--models: unknown error model '{model}'; choose from {', '.join(MODELS)}")
    return model if model == "ground-truth" else f"simulated:{model}"


# ------------------------------------------------------------------------------------------ settings
def parse_value(text: str, current, key: str, flag: str = "--refine"):
    """`text` as the type of the setting's current value."""
    kinds = ((bool, "true or false"), (int, "an integer"), (float, "a number"))
    try:
        if isinstance(current, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            return text.lower() in ("true", "1")
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
    except ValueError:
        expected = next(words for kind, words in kinds if isinstance(current, kind))
        raise ConfigError(f"{flag} {key}={text}: expected {expected}") from None
    if isinstance(current, str) or current is None:
        return text
    raise ConfigError(f"{flag} {key}: a {type(current).__name__} setting cannot be set from the command line")


def with_overrides(config, items: list[str], prefix: str = "", flag: str = "--refine"):
    """`config` (a dataclass) with KEY=VALUE items applied; `a.b=...` sets field b of the dataclass field a."""
    changes, nested = {}, {}
    names = {f.name for f in fields(config)}
    for item in items:
        key, sep, text = item.partition("=")
        head, dot, rest = key.strip().partition(".")
        if not sep or head not in names:
            known = ", ".join(prefix + name for name in sorted(names))
            raise ConfigError(f"{flag} {prefix}{item}: expected KEY=VALUE with KEY one of {known}")
        current = getattr(config, head)
        if dot:
            if not is_dataclass(current):
                raise ConfigError(f"{flag} {prefix}{item}: '{prefix}{head}' has no settings of its own")
            nested.setdefault(head, []).append(f"{rest}={text}")
        elif is_dataclass(current):
            raise ConfigError(f"{flag} {prefix}{item}: set the fields of '{prefix}{head}' as {prefix}{head}.KEY=VALUE")
        else:
            changes[head] = parse_value(text, current, prefix + key, flag)
    for head, sub in nested.items():
        changes[head] = with_overrides(getattr(config, head), sub, prefix=f"{prefix}{head}.", flag=flag)
    return replace(config, **changes)


def refine_overrides(base, items: list[str], flag: str = "--refine") -> dict:
    """The fields of the settings `base` (a RefineConfig; a GeometryConfig with flag --geometry) that `items` change."""
    changed = with_overrides(base, items, flag=flag)
    return {f.name: getattr(changed, f.name) for f in fields(base) if getattr(changed, f.name) != getattr(base, f.name)}


def size_suffix(args) -> str:
    """What the folder and result file names of a pass at another --resolution carry ("" at the preset's)."""
    return f"-{args.resolution}px" if args.resolution else ""


def protocol_config(args, predictor: str):
    """The run settings of one error model: the preset, --method, --without and setting flags (as
    `matspray run` reads them), then the --refine overrides."""
    config = build_config_from_args(args, predictor=predictor)
    if args.resolution:  # the objects' size is the size geometry trains at
        config = replace(config, geometry=replace(config.geometry, resolution=args.resolution))
    geometry = with_overrides(config.geometry, args.geometry, flag="--geometry")
    return replace(config, geometry=geometry, refine=with_overrides(config.refine, args.refine))


def object_config(config, spec: ObjectSpec):
    """`config` for one object: a simulated predictor draws its errors from the object's seed, so that
    objects do not share one realisation of the error model (wins out of N count independent draws)."""
    if not config.predictor.startswith("simulated"):
        return config
    return replace(config, predictor_options={**config.predictor_options, "seed": spec.seed})


# ------------------------------------------------------------------------------------------ geometry once
def recorded_geometry(stage_record: Path) -> dict | None:
    """The identity (`GeometryConfig.identity`) of the settings a finished geometry stage recorded; None when the
    record holds none that read as geometry settings."""
    try:
        settings = read_json(stage_record).get("settings")
        return GeometryConfig(**settings).identity() if isinstance(settings, dict) else None
    except (MatsprayError, TypeError, ValueError):
        return None


def geometry_run(runs: Path, first_model: str, geometry: GeometryConfig | None = None) -> Path:
    """The run folder whose geometry the object's other runs share: one that already has a finished
    geometry stage (from any error model, e.g. a --geometry-only pass) trained with `geometry`'s settings (as they
    apply to the protocol's objects, which have masks; any settings when None), else the first model's. A geometry
    trained with other settings (another run's predicted normals) is not one to share."""
    wanted = None if geometry is None else geometry.for_scene(masked=True).identity()
    done = sorted(
        p.parent.parent for p in runs.glob("*/geometry/stage.json") if wanted is None or recorded_geometry(p) == wanted
    )
    trained = [
        run for run in done if "geometry" in RunDir(run).timings()
    ]  # the one that trained it records its seconds
    return (trained or done or [runs / first_model])[0]


def object_geometry(data: Path, runs: Path, first_run_name: str, config, args, log) -> Path:
    """The run folder holding the object's Gaussian Splatting (`geometry_run`), trained there first if no run has it.
    Jobs for other models of the object that start meanwhile wait for it (the object's `geometry.lock`),
    then share it."""
    with held_exclusively(runs / "geometry"):
        first_run = geometry_run(runs, first_run_name, config.geometry)
        if not (first_run / "geometry" / STAGE_RECORD).exists():
            with Pipeline(data, first_run, config, progress=args.progress, log=log, wait=True) as pipeline:
                pipeline.geometry()
    return first_run


# ------------------------------------------------------------------------------------------ one run
SHARED_STAGES = ("materials2d", "lift", "visibility")  # what another configuration of a model may reuse


def configuration_key(method: str, choices: dict) -> str | None:
    """What names a configuration's run folders: None for the default method as it is, else
    `METHOD-HASH` of its choices (--without, setting flags, --refine overrides)."""
    if method == "matspray" and not any(choices.values()):
        return None
    return f"{method}-{fingerprint(choices)[:8]}"


def run_name(model: str, key: str | None) -> str:
    """The run folder of one error model under one configuration: `MODEL` for the default, else
    `MODEL-KEY`, so that configurations keep their stages side by side (compared and resumed without
    redoing each other's work)."""
    return model if key is None else f"{model}-{key}"


RUN_SECONDS = "generalise.json"  # in RUN/eval/: the seconds the run's stages and evaluation took


def finished_metrics(run_dir: Path, config, variants) -> tuple[dict, float] | None:
    """The evaluation and seconds of a run this protocol finished before with the same settings (the
    config's fingerprint recorded in RUN_SECONDS), the same variants, and no stage rewritten since; else None."""
    metrics_path, seconds_path = run_dir / "eval" / "metrics.json", run_dir / "eval" / RUN_SECONDS
    if not (metrics_path.exists() and seconds_path.exists()):
        return None
    record = read_json(seconds_path)
    if record.get("config") != fingerprint(config) or record.get("variants") != sorted(variants):
        return None
    if not newer_than_stages(metrics_path, run_dir):
        return None
    return read_json(metrics_path), float(record["seconds"])


def run_or_reuse(data: Path, run_dir: Path, config, args, log) -> tuple[dict, float]:
    """The run's metrics and seconds (without training the geometry): from a finished earlier pass (so a
    protocol over K objects can be extended to K + 1 without evaluating the first K again), else run and
    evaluated now."""
    finished = finished_metrics(run_dir, config, args.variants)
    if finished is not None:
        log(f"generalise: {run_dir}: finished before with these settings, reusing its evaluation")
        metrics, seconds = finished
        return only_variants(metrics, args.variants, RunDir(run_dir).timings()), seconds
    trains_geometry = not (run_dir / "geometry" / "stage.json").exists()
    begin = time.perf_counter()
    metrics = run_object(data, run_dir, config, variants=args.variants, progress=args.progress, log=log)
    seconds = time.perf_counter() - begin
    timings = RunDir(run_dir).timings()
    if trains_geometry:  # the geometry has its own column (trained once per object)
        seconds -= timings.get("geometry", 0.0)
    write_json(
        run_dir / "eval" / RUN_SECONDS,
        {"config": fingerprint(config), "variants": sorted(args.variants), "seconds": seconds},
    )
    return only_variants(metrics, args.variants, timings), seconds


def only_variants(metrics: dict, variants, timings: dict) -> dict:
    """`metrics` with just the variants of this configuration: the run folder may still hold assets
    that another configuration refined (evaluation scores every asset it finds)."""
    kept = {v: m for v, m in metrics.get("variants", {}).items() if v in variants}
    return {**metrics, "variants": kept, **paper_tables(kept, metrics.get("predictions_2d"), timings)}


# ------------------------------------------------------------------------------------------ protocol
def spec_record(spec: ObjectSpec) -> dict:
    """The object as its results record it (a procedural object's without the asset field it does not have)."""
    record = vars(spec) | {"relight_envs": list(spec.relight_envs)}
    return record if spec.asset is not None else {k: v for k, v in record.items() if k != "asset"}


def run_protocol(args, log=print) -> dict:
    hdris = sorted(hdri_files())
    if not hdris:
        log("notice: no ../shared/data/hdri found; objects are trained under built-in lights instead of HDRIs")
    objects = with_training_light(objects_part(args.set, args.start, args.objects, hdris), args.train_light)
    specs = {m: predictor_spec(m) for m in args.models}
    configs = {m: protocol_config(args, spec) for m, spec in specs.items()}
    first_model = args.models[0]
    base = build_config_from_args(args)
    refine = refine_overrides(base.refine, args.refine)
    geometry = refine_overrides(base.geometry, args.geometry, flag="--geometry")
    # the settings given (flags and --set), by dotted name: part of the configuration's key
    flags = {**method_settings_from_args(args), **settings_from_overrides(args.overrides, args.preset)}
    choices = {"without": list(args.without), "settings": {k: str(v) for k, v in flags.items()}, "refine": refine}
    if geometry:  # only then: the configurations run before the flag keep their names
        choices["geometry"] = geometry
    key = configuration_key(args.method, choices)
    on_normals = geometry.get("predicted_normal_weight", base.geometry.predicted_normal_weight) > 0
    geometry_key = configuration_key(  # the configuration with the geometry overrides alone (None: the default)
        "matspray", {"without": [], "settings": {}, "refine": {}, **({"geometry": geometry} if geometry else {})}
    )
    tag = args.tag or ("default" if not any(choices.values()) else fingerprint(choices)[:8])
    tag = tag if args.method == "matspray" else f"{args.method}-{tag}"
    tag = part_name(tag, args.start)  # the whole pass reuses the part's runs
    defaults = {m: default_settings(args.preset, m) for m in METHODS}  # each built once
    settings = {
        "set": args.set,
        "train_light": args.train_light,
        "preset": args.preset,
        "resolution": args.resolution or DEMO_SIZES[args.preset].res,
        "objects": len(objects),
        "start": args.start,
        "models": list(args.models),
        "variants": list(args.variants),
        "method": args.method,
        "without": list(args.without),
        "settings": choices["settings"],
        "refine_overrides": refine,
        "geometry_overrides": geometry,
        "tag": tag,
        # the defaults measured: a published pass is tied to them (benchmarks/results_defaults.py)
        "defaults": {m: fingerprint(s) for m, s in defaults.items()},
        "default_settings": defaults,
    }
    log(f"generalise: {len(objects)} {args.set} objects x {len(specs)} error models, preset {args.preset}, tag {tag}")
    if args.set in EVAL_SETS:
        log("generalise: evaluation set — run it once, with settings chosen on the development set only")
        chosen = {k: settings[k] for k in ("preset", "method", "without", "settings", "refine_overrides")}
        earlier = sorted(
            p.stem[len("results-") :]
            for p in args.out.glob("results-*.json")
            if {k: read_json(p)["settings"].get(k) for k in chosen} != chosen
        )
        if earlier:
            log(
                f"warning: this evaluation set was already run with other settings ({', '.join(earlier)}); "
                "choosing between them on it makes it a development set"
            )
    results = {m: [] for m in specs}
    timing = []
    for number, spec in enumerate(objects, 1):
        start = time.perf_counter()
        folder = args.out / "objects" / spec.name
        log(
            f"generalise: object {number}/{len(objects)} {spec.name} (train {spec.env}, "
            f"relit {', '.join(spec.relight_envs)})"
        )
        data = make_demo_object(
            folder / "data",
            args.preset,
            "random",
            spec.seed,
            progress=args.progress,
            asset=None if spec.asset is None else str(REPO_ROOT / spec.asset),
            env=spec.env,
            relight_envs=list(spec.relight_envs),
            resolution=args.resolution,
        )
        seconds = {"synth": time.perf_counter() - start, "models": {}}
        # each run trains its own where it follows its model's predicted normals (by default)
        own_geometry = on_normals and not args.geometry_only
        first_run = (
            folder / "runs" / run_name(first_model, key)
            if own_geometry
            else object_geometry(
                data, folder / "runs", run_name(first_model, key), object_config(configs[first_model], spec), args, log
            )
        )
        if args.geometry_only:
            log(
                f"generalise: {spec.name}: geometry in {first_run / 'geometry'} "
                f"({time.perf_counter() - start:.0f} s with synth)"
            )
            continue
        run_dirs = {model: folder / "runs" / run_name(model, key) for model in specs}
        for model, run_dir in run_dirs.items():
            if not own_geometry and run_dir != first_run and share_stage(first_run, run_dir, "geometry"):
                log(f"generalise: {spec.name} / {run_dir.name}: geometry shared from {first_run.name}")
            # the run to start from: the default one, or with geometry overrides the configuration that has only
            # those (its Gaussians; a lift on other Gaussians is no use)
            default_run = folder / "runs" / run_name(model, geometry_key)
            reusable = ("materials2d", "geometry", *SHARED_STAGES[1:]) if own_geometry else SHARED_STAGES
            shared = (
                [] if key == geometry_key else [stage for stage in reusable if share_stage(default_run, run_dir, stage)]
            )
            if shared:
                log(
                    f"generalise: {spec.name} / {run_dir.name}: starts from {model}'s {', '.join(shared)} (redone "
                    "where its settings differ)"
                )
            metrics, seconds["models"][model] = run_or_reuse(
                data, run_dir, object_config(configs[model], spec), args, log
            )
            results[model].append(
                {
                    "object": spec_record(spec),
                    "figures": object_figures(metrics),
                    "metrics": metrics,
                    "seconds": seconds["models"][model],
                }
            )
        # each model's own geometry (the models' seconds leave it out), or the one they share
        runs = list(run_dirs.values()) if own_geometry else [first_run]
        seconds["geometry"] = sum(RunDir(run).timings().get("geometry") or 0.0 for run in runs)
        seconds["total"] = (
            seconds["synth"] + seconds["geometry"] + sum(seconds["models"].values())
        )  # earlier passes' work included
        timing.append({"object": spec.name, **seconds})
    if args.geometry_only:
        return {
            "report": None,
            "lines": [f"geometry of {len(objects)} {args.set} objects ready in {args.out / 'objects'}"],
        }
    summaries = {m: model_summary(per_object) for m, per_object in results.items()}
    report = {
        "settings": settings,
        "timing": timing,
        "models": {
            m: {
                "summary": {k: v for k, v in summaries[m].items() if k != "tables"},
                "objects": [{k: o[k] for k in ("object", "figures", "seconds")} for o in results[m]],
            }
            for m in results
        },
    }
    lines = markdown(settings, results, summaries, timing)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / f"results-{tag}.json", report)
    write_text_atomic(args.out / f"results-{tag}.md", "\n".join(lines) + "\n")
    results_dir = getattr(args, "results_dir", None)
    if results_dir is not None and args.start == 0:  # a whole pass only: the docs' tables are made from it
        results_dir.mkdir(parents=True, exist_ok=True)
        write_json(results_dir / f"generalise-{args.set}{size_suffix(args)}-{tag}.json", report)
    for model, summary in summaries.items():
        tables = dict(
            summary["tables"],
            title=(
                f"MatSpray generalisation: {args.set} set, {len(objects)} objects, error model {model}, "
                f"preset {args.preset}"
            ),
        )
        write_tables(args.out / f"tables-{tag}-{model}.md", tables)
    return {"report": report, "lines": lines}


def parse_args(argv=None):
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.generalise",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--set",
        type=set_name,
        choices=tuple(SET_SEEDS),
        default="dev",
        help="dev, dev-b, real-dev: choose settings here; real-eval: run once, on the final defaults (default dev)",
    )
    add_part_arguments(parser)
    parser.add_argument(
        "--models", nargs="+", default=list(MODELS), metavar="MODEL", help=f"error models (default: {' '.join(MODELS)})"
    )
    parser.add_argument(
        "--variants",
        nargs="+",
        default=list(VARIANTS),
        choices=VARIANTS,
        metavar="VARIANT",
        help=f"variants refined per run (default: {' '.join(VARIANTS)})",
    )
    parser.add_argument(
        "--refine",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="override refinement settings (RefineConfig fields, "
        "merger.KEY for the merger), e.g. --refine iterations=300 merger.hidden=64",
    )
    parser.add_argument(
        "--geometry",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="override geometry settings (GeometryConfig fields), e.g. --geometry predicted_normal_weight=0: one "
        "geometry per object, shared by its models (by default each run trains its own on its model's normals)",
    )
    parser.add_argument(
        "--tag", help="name of this configuration's results files (default: 'default', or a hash of the overrides)"
    )
    parser.add_argument(
        "--out", type=Path, help="folder (default runs/generalise-SET-PRESET); objects and runs in it are reused"
    )
    parser.add_argument(
        "--results-dir",
        type=Path,
        help="where a whole pass's results are also written as generalise-SET-TAG.json, "
        "the files the docs' tables are made from (python -m benchmarks.tables); default docs/results when --out is "
        "left at its default, else nowhere",
    )
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    parser.add_argument(
        "--geometry-only",
        action="store_true",
        help="make the objects and train their geometry only (shared by every "
        "later configuration), e.g. in the background while settings are still being chosen",
    )
    parser.add_argument(
        "--compare",
        action="store_true",
        help="run nothing: print one row per configuration already run in --out "
        "(its results-*.json), the table to choose settings from",
    )
    parser.add_argument(
        "--resolution",
        type=int,
        metavar="PX",
        help="render the objects at PX and train at that size (default: the preset's, demo 128); "
        "its own folder (default --out runs/generalise-SET-PRESET-PXpx)",
    )
    parser.add_argument(
        "--train-light", metavar="NAME", help="train every object under this light instead of its own (e.g. sunset)"
    )
    add_method_arguments(parser, presets=("test", "demo"))
    add_set_argument(parser, flag="--setting")  # (its --set names the object set)
    args = parser.parse_args(argv)
    check_part_arguments(parser, args)
    if args.resolution is not None and args.resolution < 8:
        parser.error(f"--resolution must be >= 8 px (got {args.resolution})")
    if args.results_dir is None and args.out is None:
        args.results_dir = Path("docs") / "results"
    args.out = args.out or Path("runs") / f"generalise-{args.set}-{args.preset}{size_suffix(args)}"
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        if args.compare:
            print("\n".join(choices_table(args.out)))
            return 0
        result = run_protocol(args)
    except MatsprayError as exc:
        print(f"error: {flag_message(exc)}", file=sys.stderr)
        return 2
    print("\n" + "\n".join(result["lines"]))
    if result["report"] is None:
        return 0
    print(
        f"\nwritten: {args.out / ('results-' + result['report']['settings']['tag'] + '.md')} (and .json, tables-*.md)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
