"""Photos cut to their object before the working size: two runs of one capture without masks, one with
its photos cut (the default) and one with them whole (`--set crop.enabled=false`), side by side.

    python -m benchmarks.crop_detail --cut RUN --whole RUN

Printed per run: the Gaussians of the geometry and how many of them are inside the object region; the held-out
views scored inside the object mask, both at the whole photo's working size (the whole run's views and masks) and
at the crop's (the cut run's), for the geometry's own colours (radiance) and for each asset under the light it
estimated; and the seconds of each stage. Both runs are scored on the same views with the same masks.
"""

from __future__ import annotations

import argparse

from matspray.data import load_run_scene
from matspray.errors import ConfigError
from matspray.eval.heldout import photo_renders, read_renderables, score_photos, view_masks
from matspray.eval.lpips import load_lpips
from matspray.rundir import RunDir, read_record


def object_share(run: RunDir) -> tuple[int, int]:
    """(Gaussians inside the object region, Gaussians of the geometry)."""
    masks = read_record(run.path("masks", "stage.json"), "run `matspray run` on it to the end")
    metrics = read_record(run.path("geometry", "metrics.json"), "run `matspray run` on it to the end")
    return int(masks["inside"]), int(metrics["gaussians"])


def heldout(runs: dict[str, RunDir], lpips) -> dict[str, dict[str, dict]]:
    """{view set: {run name: score_photos' summary}}: every run on the test views (and masks) of each run."""
    scores: dict[str, dict[str, dict]] = {}
    renderables = {name: read_renderables(run) for name, run in runs.items()}
    for owner, run in runs.items():
        views = load_run_scene(run).test
        masks = view_masks(run, views, "test")
        for name, other in runs.items():
            rendered = photo_renders(other, views, "test", progress=False, renderables=renderables[name], masks=masks)
            scores.setdefault(owner, {})[name] = score_photos(rendered, lpips)["summary"]
    return scores


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cut", required=True, help="the run whose photos were cut to the object")
    parser.add_argument("--whole", required=True, help="the run of the same capture with crop.enabled=false")
    args = parser.parse_args(argv)
    runs = {"cut": RunDir(args.cut).require(), "whole": RunDir(args.whole).require()}
    if runs["cut"].dataset()["source"] != runs["whole"].dataset()["source"]:
        raise ConfigError("--cut and --whole must be runs of the same capture")
    lpips, _ = load_lpips()
    scores = heldout(runs, lpips)
    renders = list(scores["whole"]["whole"])
    print("| run | Gaussians | on the object | " + " | ".join(f"{r} (whole photo / crop)" for r in renders) + " |")
    print("|---|---:|---:|" + "---:|" * len(renders))
    for name, run in runs.items():
        inside, total = object_share(run)
        cells = [f"{scores['whole'][name][r]['psnr']:.2f} / {scores['cut'][name][r]['psnr']:.2f} dB" for r in renders]
        print(f"| {name} | {total} | {inside} ({100 * inside / total:.0f} %) | " + " | ".join(cells) + " |")
    print()
    for name, run in runs.items():
        timings = run.timings()
        total = sum(timings.values())
        print(f"{name}: stages " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()) + f" (sum {total:.0f} s)")


if __name__ == "__main__":
    main()
