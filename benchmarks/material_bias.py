"""Signed error of each variant's materials on the object, against the 2D predictions'.

    python -m benchmarks.material_bias RUN [RUN ...] [--channels roughness metallic basecolor]

For every finished run of a `matspray synth` object: each variant's asset (the full method and the
ablations found in the run folder) rasterized in the test views, and the run predictor's raw 2D maps of
the same views, compared with the true maps on the object (ground-truth mask >= 0.5). Prints per
channel the mean signed error (prediction - truth; base colour: mean over RGB, linear), the mean
absolute error and the RMSE.

A systematic error shared by every view (the simulated predictor's tone curve lowers roughness in all of
them) shows as a signed error of the 2D row; a merger that can only weight the views' estimates
(softmax) keeps a Gaussian inside their range, so this tells how much of that bias each variant keeps.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from matspray.data import load_run_scene
from matspray.errors import MatsprayError
from matspray.eval.run_eval import GroundTruth, asset_renders, predict_test_views, read_view_truth
from matspray.method.asset import read_asset
from matspray.presets import VARIANTS, asset_stage
from matspray.rundir import RunDir

CHANNELS = ("roughness", "metallic", "basecolor")


def scalar_map(maps, channel: str) -> torch.Tensor:  # [H, W] or [H, W, 3] -> [H, W]
    values = getattr(maps, "base_color" if channel == "basecolor" and hasattr(maps, "base_color") else channel)
    return values.mean(-1) if values.dim() == 3 else values


def error_stats(predictions: list[torch.Tensor], truths: list[GroundTruth], channel: str) -> dict:
    """Signed mean, mean absolute and RMS error of [H, W] maps against the truths, on the object."""
    errors = torch.cat(
        [(p - scalar_map(t, channel))[t.mask >= 0.5].reshape(-1) for p, t in zip(predictions, truths)]
    ).double()
    return {
        "signed": float(errors.mean()),
        "abs": float(errors.abs().mean()),
        "rmse": float(errors.pow(2).mean().sqrt()),
    }


def run_bias(run: Path, channels) -> dict[str, dict[str, dict]]:
    """row name ('full', ..., '2D') -> channel -> error statistics, for one run."""
    run_dir = RunDir(run)
    views = load_run_scene(run_dir).test
    truths = [read_view_truth(view) for view in views]
    rows = {}
    for variant in VARIANTS:
        if not (run / asset_stage(variant)).exists():
            continue
        asset = read_asset(run / asset_stage(variant))
        renders = [asset_renders(asset, view, {}) for view in views]
        rows[variant] = {c: error_stats([scalar_map(r, c) for r in renders], truths, c) for c in channels}
    maps, _ = predict_test_views(run, views)
    if maps is not None:
        rows["2D"] = {c: error_stats([scalar_map(maps[v.name], c) for v in views], truths, c) for c in channels}
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, metavar="RUN", help="finished run folders of synth objects")
    parser.add_argument("--channels", nargs="+", choices=CHANNELS, default=list(CHANNELS))
    args = parser.parse_args(argv)
    torch.set_grad_enabled(False)
    for run in args.runs:
        try:
            rows = run_bias(run, args.channels)
        except (MatsprayError, FileNotFoundError) as exc:
            print(f"{run}: {exc}")
            return 1
        print(f"\n{run}: error on the object, test views (signed = prediction - truth)")
        print("| row | " + " | ".join(f"{c} signed | {c} abs | {c} rmse" for c in args.channels) + " |")
        print("| --- |" + " ---: |" * (3 * len(args.channels)))
        for name, stats in rows.items():
            cells = " | ".join(
                f"{stats[c]['signed']:+.3f} | {stats[c]['abs']:.3f} | {stats[c]['rmse']:.3f}" for c in args.channels
            )
            print(f"| {name} | {cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
