"""How many Gaussians the Neural Merger runs for per refinement step, by `refine.min_coverage`.

    python -m benchmarks.merger_coverage --data DATA --run RUN [--thresholds 0 0.02 0.2 0.5] [--views 10]

On a run whose geometry and lift are done with the preset's default settings and the simulated predictor (a
`matspray demo` run, or `matspray run --predictor simulated` without --set: its stages are reused and nothing is
written; a run made with other settings would have those stages redone in its folder), for each threshold: the
mean, over `--views` training views spread over the set, of the Gaussians that cover at least that many pixels of
the view (`FrozenViews.contributing_ids`: the ones the merger runs for; the others keep their last value).
The merger's batched matrix products are most of a refinement step's time on a CPU, so a step's cost follows this
count (docs/dev/demo-time.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matspray.method.config import build_config
from matspray.method.pipeline import Pipeline
from matspray.method.refine.loop import frozen_views


def covered_counts(frozen, thresholds: list[float], views: int) -> dict[float, float]:
    """Mean number of Gaussians at or above each coverage threshold, over `views` evenly spread views."""
    n_views = len(frozen.visible_ids)
    picked = sorted({round(i * n_views / views) for i in range(min(views, n_views))})
    return {t: sum(len(frozen.contributing_ids(i, t)) for i in picked) / len(picked) for t in thresholds}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, type=Path, help="the run's dataset folder")
    parser.add_argument("--run", required=True, type=Path, help="a run folder with geometry and lift done")
    parser.add_argument("--preset", default="demo")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.0, 0.02, 0.05, 0.1, 0.2, 0.5])
    parser.add_argument("--views", type=int, default=10, help="training views to average over")
    args = parser.parse_args(argv)
    config = build_config(args.preset, predictor="simulated")
    with Pipeline(args.data, args.run, config, progress=False, log=lambda *_: None) as pipeline:
        inputs = pipeline.refine_inputs()
        frozen = frozen_views(inputs)
        print(f"{len(inputs.gaussians)} Gaussians; merger per step, mean over {args.views} views:")
        for threshold, count in covered_counts(frozen, args.thresholds, args.views).items():
            print(f"  min_coverage {threshold:<5g} {count:9.0f}")


if __name__ == "__main__":
    main()
