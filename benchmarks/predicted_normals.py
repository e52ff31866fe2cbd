"""Mean angular error of the simulated predictor's normals, per error model, on synthetic objects.

    python -m benchmarks.predicted_normals --data OBJECT [OBJECT ...] [--models paper harsh outliers dr] [--search]

For each `matspray synth` object folder, every error model predicts the object's TEST views (with the
object's seed, as a run's evaluation does) and the predicted normals are compared with the true ones
(`{view}_normal.exr`): the mean angle in degrees over the object's pixels (alpha > 0.5) of each view,
averaged over the views, then over the objects. Prints one markdown row per object and model.

`--search` finds `dr`'s normal scale (matspray.predictors.error_models.dr_model's `normal_scale`: `paper`'s
normal tilts and blur times a factor) by bisection towards DR_NORMAL_TARGET_DEG, then scores the result;
DR_NORMAL_SCALE is its final midpoint, rounded. Only the predictions' own error is measured.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from matspray.data.formats import blender
from matspray.data.scene import View
from matspray.errors import MatsprayError
from matspray.predictors.error_models import (
    DR_COLOUR_SCALE,
    DR_METALLIC_VIEW_FRACTION,
    DR_NORMAL_TARGET_DEG,
    DR_ROUGHNESS_COMPRESSION,
    ERROR_MODELS,
    SimulationConfig,
    dr_model,
)
from matspray.predictors.ground_truth import read_ground_truth_normals
from matspray.predictors.normalmaps import mean_angular_error_deg
from matspray.predictors.registry import object_seed
from matspray.predictors.simulated import SimulatedPredictor

BRACKET = (0.0, 4.0)  # where the bisection looks for dr's normal scale


def view_errors(config: SimulationConfig, views: list[View], seed: int) -> list[float]:
    """Mean angular error (degrees) of each view's simulated normals on the object (alpha > 0.5)."""
    maps = SimulatedPredictor(replace(config, seed=seed)).predict(views)
    errors = []
    for view in views:
        truth = read_ground_truth_normals(view)
        if truth is None or maps[view.name].normals is None:
            raise MatsprayError(f"view '{view.name}' has no true normals ({view.path}): not a `matspray synth` object")
        mask = view.alpha > 0.5 if view.alpha is not None else None
        errors.append(mean_angular_error_deg(maps[view.name].normals, truth, mask))
    return errors


def load_objects(folders: list[Path]) -> list[tuple[str, list[View], int]]:
    """(name, test views, synth seed) of each object folder."""
    objects = []
    for folder in folders:
        views = blender.read_split(folder, "test")
        if not views:
            raise MatsprayError(f"{folder}: no test views")
        objects.append((folder.parent.name if folder.name == "data" else folder.name, views, object_seed(folder) or 0))
    return objects


def mean_error(config: SimulationConfig, objects) -> tuple[list[float], float]:
    per_object = [sum(e) / len(e) for e in (view_errors(config, views, seed) for _, views, seed in objects)]
    return per_object, sum(per_object) / len(per_object)


def error_table(models: dict[str, SimulationConfig], objects) -> list[str]:
    lines = ["| model | object | mean angular error (deg) |", "|---|---|---|"]
    for name, config in models.items():
        per_object, mean = mean_error(config, objects)
        lines += [f"| `{name}` | {obj[0]} | {err:.2f} |" for obj, err in zip(objects, per_object)]
        lines.append(f"| `{name}` | **mean of {len(objects)}** | {mean:.2f} |")
    return lines


def dr_with(normal_scale: float) -> SimulationConfig:
    return dr_model(DR_COLOUR_SCALE, DR_ROUGHNESS_COMPRESSION, DR_METALLIC_VIEW_FRACTION, normal_scale)


def bisect(objects, steps: int, log=print) -> float:
    """`dr`'s normal scale whose mean error meets DR_NORMAL_TARGET_DEG (the error grows with the scale)."""
    low, high = BRACKET
    log("| step | normal scale | mean angular error (deg) |\n|---|---|---|")
    for step in range(1, steps + 1):
        mid = 0.5 * (low + high)
        _, mean = mean_error(dr_with(mid), objects)
        log(f"| {step} | {mid:.4f} | {mean:.2f} |")
        low, high = (mid, high) if mean < DR_NORMAL_TARGET_DEG else (low, mid)
    return 0.5 * (low + high)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.predicted_normals",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="`matspray synth` object folders")
    parser.add_argument("--models", nargs="+", default=list(ERROR_MODELS), choices=tuple(ERROR_MODELS), metavar="MODEL")
    parser.add_argument("--search", action="store_true", help="first bisect dr's normal scale, then score it too")
    parser.add_argument("--steps", type=int, default=7, help="bisection steps (default 7)")
    args = parser.parse_args(argv)
    try:
        objects = load_objects(args.data)
        models = {name: ERROR_MODELS[name] for name in args.models}
        if args.search:
            scale = bisect(objects, args.steps)
            print(f"\ndr normal scale: {scale:.4f} (target {DR_NORMAL_TARGET_DEG} deg)\n")
            models["dr (searched)"] = dr_with(scale)
        print("\n".join(error_table(models, objects)))
    except MatsprayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
