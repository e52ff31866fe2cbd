"""Relit crops of the object, before and after: the same held-out camera and light for several runs of one capture,
each cropped to the object and brought to the same size, beside the photo (the "report before/after"); for a
`matspray synth` object with relit truth under ENV (one of its held-out lights), beside that truth, lit by the
object's own map of ENV.

    python -m benchmarks.relit_crops --runs BEFORE AFTER [--labels before after] --view 0009 [--env studio]
        --out docs/images/stitch_focus.png [--size 256]

`matspray.eval.relit_crops` makes the row (the capture report's `matspray eval --compare` shows the same): each run's
default asset relit under ENV with the first run's camera of that test view, over grey, the square around the union of
the runs' object pixels (alpha >= 0.5) with a margin, the same for every column.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matspray.data import load_run_scene
from matspray.data.images import write_image
from matspray.eval.capture_report import RELIGHT_ENV_HEIGHT
from matspray.eval.relit_crops import default_asset, relit_crops, relit_truth, same_capture
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import load_envmap
from matspray.rundir import RunDir


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", type=Path, required=True)
    parser.add_argument("--labels", nargs="+", help="one per run (printed with the figure's columns)")
    parser.add_argument("--view", required=True, help="a test view of the runs' dataset, e.g. 0009")
    parser.add_argument("--env", default="studio")
    parser.add_argument("--size", type=int, default=256, help="side of each column in pixels")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.labels and len(args.labels) != len(args.runs):
        parser.error(f"{len(args.labels)} labels for {len(args.runs)} runs")

    runs = [RunDir(path).require() for path in args.runs]
    same_capture(runs)
    test = load_run_scene(runs[0]).test
    view = next((v for v in test if v.name == args.view), None)
    if view is None:
        parser.error(f"no test view {args.view} in {runs[0].dataset()['source']}: {', '.join(v.name for v in test)}")
    truth = relit_truth(view, args.env, Path(runs[0].dataset()["source"]))
    if truth is not None:  # a synthetic object: its truth under that held-out light, and the light it was made with
        reference, environment = truth
        name, first = args.env, "the truth relit"
    else:
        name, env = load_envmap(args.env, height=RELIGHT_ENV_HEIGHT)  # as the capture report relights
        reference, environment, first = view.image, EnvironmentMap.from_tensor(env, learnable=False), "photo"
    light = environment.prefilter()
    row = relit_crops([default_asset(run) for run in runs], view.camera, light, reference, args.size)
    if row is None:
        raise SystemExit(f"no run covers any pixel of view {args.view} with its object")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_image(args.out, row)
    labels = args.labels or [str(path) for path in args.runs]
    print(f"wrote {args.out}: view {args.view} under {name}; columns: {first}, " + ", ".join(labels))


if __name__ == "__main__":
    main()
