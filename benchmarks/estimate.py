"""The rates behind `matspray run`'s time estimate (matspray/method/estimate.py), measured on finished runs.

    python -m benchmarks.estimate RUN [RUN ...]

For every run and stage: the stage's work (estimate.Work's units, from the run's own settings and views), the seconds
its timings.json recorded and their ratio (the rate). Then the median rate per stage beside the one estimate.py uses,
and per run the estimate made with estimate.py's rates against the time the run took (stages it trained itself). Only
runs made with the numba rasterizer on the CPU count: the rates are the reference machine's."""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from matspray.data.loader import load_run_scene
from matspray.method.estimate import CPU_RATES, estimate_error, feature_sizes, run_work
from matspray.presets import get_variant
from matspray.rundir import STAGE_RECORD, RunDir, read_json


def stage_work(run: Path) -> dict[str, tuple[float, float]]:
    """{stage: (units of work, seconds)} for the stages `run` ran itself (asset stages under the name `refine`)."""
    folder = RunDir(run)
    config, timings = folder.config(), folder.timings()
    scene = load_run_scene(folder)
    views = [(v.width, v.height) for v in scene.train]
    rays = 1 if config.get("predictor") == "none" else config["lift"]["samples_per_side"] ** 2
    longest = config.get("points", {}).get("max_size", 0)  # runs made before the points stage have none
    features = feature_sizes(views, scene.downscale, longest) if longest else []
    work = run_work(
        views,
        config["geometry"]["iterations"],
        config["geometry"]["resolution"],
        rays,
        [],
        not scene.has_masks,
        feature_views=features,
    )
    pixels = sum(w * h for w, h in views) / len(views)
    found = {}
    for stage, seconds in timings.items():
        record = folder.path(stage, STAGE_RECORD)
        if not record.exists() or read_json(record).get("backend", "numba") != "numba":
            continue
        if stage.startswith("asset"):
            found[stage] = (read_json(record)["settings"]["iterations"] * pixels, seconds)
        elif stage in ("points", "geometry", "masks", "lift"):
            found[stage] = (getattr(work, stage), seconds)
    return found


def stage_kind(stage: str) -> str:
    """The rate a run-folder stage is estimated with: asset stages by whether their variant merges 2D maps."""
    if not stage.startswith("asset"):
        return stage
    variant = "full" if stage == "asset" else stage[len("asset-") :]
    return "refine" if get_variant(variant).uses_maps else "refine-mapless"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args(argv)
    rates: dict[str, list[float]] = {}
    totals = []
    print("| run | stage | work | s | rate |\n|---|---|---:|---:|---:|")
    for run in args.runs:
        measured = stage_work(run)
        for stage, (units, seconds) in measured.items():
            kind = stage_kind(stage)
            if units > 0 and seconds > 0:
                rates.setdefault(kind, []).append(seconds / units)
            print(f"| {run} | {stage} | {units:.3g} | {seconds:.0f} | {seconds / max(units, 1e-30):.2e} |")
        estimated = sum(units * CPU_RATES[stage_kind(s)] for s, (units, _) in measured.items())
        taken = sum(seconds for _, seconds in measured.values())
        totals.append((run, estimated, taken))
    print("\n| stage | runs | median rate | estimate.py |\n|---|---:|---:|---:|")
    for stage, values in rates.items():
        print(f"| {stage} | {len(values)} | {statistics.median(values):.2e} | {CPU_RATES[stage]:.2e} |")
    print("\n| run | estimated s | taken s | factor |\n|---|---:|---:|---:|")
    for run, estimated, taken in totals:
        print(f"| {run} | {estimated:.0f} | {taken:.0f} | {estimate_error(estimated, taken):.2f} |")
    factors = [estimate_error(e, t) for _, e, t in totals]
    print(f"\nworst factor {max(factors):.2f}, median {statistics.median(factors):.2f} over {len(factors)} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
