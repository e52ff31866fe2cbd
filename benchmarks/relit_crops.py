"""Relit crops of the object, before and after: the same held-out camera and light for several runs of one capture,
each cropped to the object and brought to the same size, beside the photo (issue 55's "report before/after").

    python -m benchmarks.relit_crops --runs BEFORE AFTER [--labels before after] --view 0009 [--env studio]
        --out docs/images/stitch_focus.png [--size 256]

Each run's asset is relit with `matspray relight --run RUN --env ENV` (its test cameras, transparent PNGs, into
RUN/relit-crops/ ; reused when there). The crop is the square around the union of the runs' object pixels in that
view (alpha >= 0.5) with a margin, the same for every column; columns: the photo, then each run, over grey.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from matspray.data import load_scene
from matspray.data.images import read_image, resize, write_image
from matspray.rundir import RunDir

GREY = 0.5  # linear background of the crops
MARGIN = 0.08  # of the crop's side, around the object


def relit_view(run: Path, view: str, env: str) -> tuple[np.ndarray, np.ndarray]:
    """The run's asset relit under `env` in test view `view`: linear RGB [H, W, 3] and alpha [H, W]."""
    folder = run / "relit-crops"
    path = folder / f"{view}_{env}.png"
    if not path.exists():
        command = [sys.executable, "-m", "matspray", "relight", "--run", str(run), "--env", env, "--out", str(folder)]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(command[1:])} failed:\n{done.stderr[-2000:]}")
    image, alpha = read_image(path)
    return image.numpy(), alpha.numpy()


def square_box(alphas: list[np.ndarray]) -> tuple[int, int, int]:
    """(row, column, side) of the square around every alpha's object pixels, with a margin, inside the image."""
    covered = np.any([a >= 0.5 for a in alphas], axis=0)
    rows, cols = np.nonzero(covered)
    if len(rows) == 0:
        raise SystemExit("no run covers any pixel of that view with its object")
    height, width = covered.shape
    side = int(max(rows.max() - rows.min(), cols.max() - cols.min()) * (1 + 2 * MARGIN)) + 1
    side = min(side, height, width)
    top = int(np.clip((rows.min() + rows.max() - side) // 2, 0, height - side))
    left = int(np.clip((cols.min() + cols.max() - side) // 2, 0, width - side))
    return top, left, side


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

    relit = [relit_view(run, args.view, args.env) for run in args.runs]
    top, left, side = square_box([alpha for _, alpha in relit])
    photo = next((v for v in test_photos(args.runs[0]) if v.name == args.view), None)
    columns = []
    if photo is not None and photo.image.shape[:2] == relit[0][0].shape[:2]:
        columns.append(photo.image.numpy())
    for image, alpha in relit:
        columns.append(image * alpha[..., None] + GREY * (1 - alpha[..., None]))
    crops = [
        resize(torch.from_numpy(np.ascontiguousarray(c[top : top + side, left : left + side])), args.size, args.size)
        for c in columns
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_image(args.out, torch.cat(crops, dim=1))
    names = (["photo"] if len(columns) > len(relit) else []) + (args.labels or [str(r) for r in args.runs])
    print(
        f"wrote {args.out}: view {args.view} under {args.env}, crop {side} px at ({top}, {left}); columns: "
        + ", ".join(names)
    )


def test_photos(run: Path):
    """The test views of the dataset `run` was made from, at the run's working size."""
    folder = RunDir(run).require()
    return load_scene(folder.dataset()["source"], downscale=folder.downscale()).test


if __name__ == "__main__":
    main()
