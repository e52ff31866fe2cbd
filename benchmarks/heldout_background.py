"""The whole-image held-out PSNR of runs' geometry on captures without masks, its render over black (what training
composites on, and what `evaluate_views` uses for such views) against over white (what it used before): the part of
a dark backdrop no training view saw turned white.

    python -m benchmarks.heldout_background RUN [RUN ...]

Each RUN is a run folder whose geometry stage is done; its test views are loaded at the run's working size.
"""

from __future__ import annotations

import argparse

import torch

from matspray.data import load_scene
from matspray.geometry.evaluate import evaluate_views
from matspray.geometry.ply import read_ply
from matspray.geometry.train import prepare_views
from matspray.rundir import RunDir


def compare(run: RunDir) -> dict:
    dataset = run.dataset()
    gaussians, _ = read_ply(run.path("geometry", "gaussians.ply"))
    names = set(dataset["test_views"])
    test = prepare_views(load_scene(dataset["source"]).test, max(dataset["resolution"]))
    views = [v for v in test if v.name in names]
    unmasked = [v for v in views if v.alpha is None]
    return {
        "views": len(unmasked),
        "over white": evaluate_views(gaussians, unmasked, background=torch.ones(3))["psnr"],
        "over black": evaluate_views(gaussians, unmasked, background=torch.zeros(3))["psnr"],
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders with a finished geometry stage")
    args = parser.parse_args(argv)
    print("| run | unmasked test views | whole-image PSNR over white (before) | over black (now) |")
    print("|---|---|---|---|")
    for path in args.runs:
        row = compare(RunDir(path))
        if not row["views"]:
            print(f"| {path} | 0 (the capture has masks) | | |")
            continue
        print(f"| {path} | {row['views']} | {row['over white']:.2f} dB | {row['over black']:.2f} dB |")


if __name__ == "__main__":
    main()
