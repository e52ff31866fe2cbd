"""Where the 3D metallic loses against the truth: its error split over parts of the test views.

    python -m benchmarks.metallic_parts [--set dev] [--objects 3] [--model dr] [--radius 2]
        [--rows 2D=dr-matspray-0f581f72 "lifted truth=ground-truth-on-dr-matspray-0f581f72/asset-proj-average"
                lift=dr-matspray-0f581f72/asset-proj-average full=dr-matspray-37fb3a8b/asset]
        [--fit-to-truth "lifted truth" [--fit-steps 1200]] [--out DIR]

Reads the runs `python -m benchmarks.generalise` left in OUT (default runs/generalise-SET-demo); each row is
LABEL=RUN/ASSET (a run folder under OBJECT/runs and the asset in it, `MODEL` in RUN replaced by --model), or
2D=RUN: that run's predictor's own maps of the test views (predicted again, as the evaluation does). The defaults are
the `gn1r1` pass of docs/dev/normals.md: `lift` is the mean of the lifted predictions (proj-average) and `full` the
Neural Merger's after refinement, both on the Gaussians of Gaussian Splatting on predicted normals; `lifted truth`
the true maps lifted onto the same Gaussians.

The metallic metric (`matspray.eval.metallic`) pools the squared error of every test view's map, composited with
the true mask on black, over the whole image. Each pixel's error is put into one part of the true view:
  silhouette   on the object (true mask > 0) within RADIUS px of its outline (or partly covered)
  edge         further inside, within RADIUS px of a change of the true metallic (its range over the
               (2 RADIUS + 1)^2 window > EDGE_STEP)
  interior     the rest of the object: `metal` where the true metallic is >= 0.5, `dielectric` below
`--fit-to-truth LABEL ...` adds, for those rows, the asset with its metallic fitted to the TRUE training maps through
the renderer (`matspray.method.refine.metallic` without pull or photos): on the lifted truth, what per-Gaussian values
could show on these Gaussians, so the part of its error the lift causes and the part the Gaussians' footprint does.
For every part: its share of the pixels, its share of the error, its own PSNR (its mean error) and what the whole
figure would gain were that part exact (dB). These figures are one object's pooled views, averaged over objects.
The metallic PSNR is shown twice: pooled over the views (how `matspray eval` scores the 3D metallic) and the mean of
the views' own PSNRs (how it scores the 2D predictions' metallic; never below the pooled figure).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from matspray.metrics import psnr_from_mse as psnr

EDGE_STEP = 0.1  # a change of the true metallic larger than this is an edge (its levels differ by >= 0.25 here)
PARTS = ("silhouette", "edge", "interior metal", "interior dielectric")
DEFAULT_ROWS = (
    "2D=MODEL-matspray-0f581f72",
    "lifted truth=ground-truth-on-MODEL-matspray-0f581f72/asset-proj-average",
    "lift=MODEL-matspray-0f581f72/asset-proj-average",
    "full=MODEL-matspray-37fb3a8b/asset",
)


def dilate(flags: torch.Tensor, radius: int) -> torch.Tensor:  # [V, H, W] bool -> [V, H, W] bool
    """Pixels within `radius` (Chebyshev) of a set pixel."""
    if radius == 0:
        return flags
    return F.max_pool2d(flags[:, None].float(), 2 * radius + 1, stride=1, padding=radius)[:, 0] > 0


def local_range(values: torch.Tensor, radius: int) -> torch.Tensor:  # [V, H, W] -> [V, H, W]
    """Max minus min of `values` over each pixel's (2 radius + 1)^2 window (edges padded by replication)."""
    size = 2 * radius + 1
    padded = F.pad(values[:, None], (radius,) * 4, mode="replicate")
    return (F.max_pool2d(padded, size, stride=1) + F.max_pool2d(-padded, size, stride=1))[:, 0]


def metallic_parts(truth: torch.Tensor, mask: torch.Tensor, radius: int) -> dict[str, torch.Tensor]:
    """The parts of `PARTS` ([V, H, W] bool each, disjoint, covering the object) of views with true metallic
    `truth` [V, H, W] and true mask `mask` [V, H, W]."""
    on_object = mask > 0
    # the core: pixels whose whole window is fully covered object; its edges cannot be the outline's
    core = ~dilate(mask < 1, radius)
    silhouette = on_object & ~core
    edge = core & (local_range(truth, radius) > EDGE_STEP)
    inside = core & ~edge
    return {
        "silhouette": silhouette,
        "edge": edge,
        "interior metal": inside & (truth >= 0.5),
        "interior dielectric": inside & (truth < 0.5),
    }


def squared_errors(pred: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-pixel squared error [V, H, W] as `matspray.eval.metallic` pools it (both composited with the true mask
    on black)."""
    return ((pred.double() - truth.double()) * mask.double()) ** 2


def part_figures(errors: torch.Tensor, parts: dict[str, torch.Tensor]) -> dict:
    """PSNR of the pooled `errors` [V, H, W] and, per part: pixels (share of the object), error share, the part's
    own PSNR and the gain (dB) were it exact."""
    total = float(errors.sum())
    pixels = errors.numel()
    on_object = sum(int(p.sum()) for p in parts.values())
    # the pooled figure is how `matspray eval` scores the 3D and the 2D metallic alike (`matspray.eval.metallic`); the
    # mean of the views' own PSNRs (`psnr_views`), the 2D rule before 2026-11-28, is the higher, by Jensen's inequality
    per_view = errors.flatten(1).mean(1)
    figures = {"psnr": psnr(total / pixels), "view_mean": sum(psnr(float(e)) for e in per_view) / len(per_view)}
    for name, flags in parts.items():
        part = float(errors[flags].sum())
        count = int(flags.sum())
        figures[name] = {
            "pixels": count / max(on_object, 1),
            "error": part / total if total > 0 else 0.0,
            "psnr": psnr(part / max(count, 1)),
            "gain": psnr((total - part) / pixels) - figures["psnr"],
        }
    return figures


def rendered_metallic(asset, views) -> torch.Tensor:  # -> [V, H, W]
    """The asset's metallic at every view (its G-buffer, divided by coverage, clamped as the evaluation does)."""
    from matspray.eval.run_eval import asset_renders

    return torch.stack([asset_renders(asset, view, {}).metallic for view in views])


def row_metallic(row: str, runs: Path, model: str, views) -> torch.Tensor:
    """[V, H, W] metallic of one row (`LABEL=RUN/ASSET` or `2D=RUN`) on the test views."""
    label, _, where = row.partition("=")
    where = runs / where.replace("MODEL", model)
    if label == "2D":
        from matspray.eval.run_eval import predict_test_views

        maps, note = predict_test_views(where, views)
        if maps is None:
            raise SystemExit(f"error: {note}")
        return torch.stack([maps[v.name].metallic for v in views])
    from matspray.method.asset import read_asset

    return rendered_metallic(read_asset(where), views)


def fitted_to_truth(asset, train_views, steps: int) -> torch.Tensor:  # -> [N] metallic
    """The asset's metallic fitted through its frozen training views to the TRUE metallic maps (`fit_metallic` with
    no pull and no photos): what per-Gaussian values could show on these Gaussians, whatever the lift."""
    from matspray.method.refine.metallic import MetallicFitConfig, fit_metallic
    from matspray.predictors.ground_truth import read_ground_truth
    from matspray.render.raster.gbuffer import FrozenViews

    frozen = FrozenViews(asset.gaussians, [v.camera for v in train_views])
    targets = [read_ground_truth(v).metallic for v in train_views]
    surfaces = [v.alpha * (alpha > 0.5) for v, alpha in zip(train_views, frozen.alphas)]
    config = MetallicFitConfig(steps=steps, pull=0.0, lr=0.02, photo_weight=0.0)
    return fit_metallic(asset.materials[:, 4], frozen.render, targets, surfaces, config)


def object_rows(data: Path, runs: Path, model: str, rows: list[str], radius: int, fit: list[str], steps: int) -> dict:
    """{label: part_figures} of one object; each row labelled in `fit` also fitted to the true maps (`steps`)."""
    from dataclasses import replace

    from matspray.data import load_scene
    from matspray.eval.run_eval import read_view_truth
    from matspray.method.asset import read_asset

    scene = load_scene(data)
    views = scene.test
    truths = [read_view_truth(v) for v in views]
    truth = torch.stack([t.metallic for t in truths]).double()
    mask = torch.stack([t.mask for t in truths]).double()
    parts = metallic_parts(truth, mask, radius)
    figures = {}
    for row in rows:
        label, _, where = row.partition("=")
        figures[label] = part_figures(squared_errors(row_metallic(row, runs, model, views), truth, mask), parts)
        if label in fit:
            asset = read_asset(runs / where.replace("MODEL", model))
            metallic = fitted_to_truth(asset, scene.train, steps)
            materials = torch.cat([asset.materials[:, :4], metallic[:, None]], dim=1)
            fitted = rendered_metallic(replace(asset, materials=materials), views)
            figures[f"{label}, fitted to the true maps"] = part_figures(squared_errors(fitted, truth, mask), parts)
    return figures


def mean_figures(per_object: list[dict]) -> dict:
    """The mean of every figure over objects (same keys)."""
    first = per_object[0]
    if isinstance(first, dict):
        return {key: mean_figures([o[key] for o in per_object]) for key in first}
    return sum(per_object) / len(per_object)


def table(label: str, figures: dict) -> list[str]:
    lines = [
        f"#### {label}",
        "",
        "| row | metallic PSNR, pooled / mean of views | "
        + " | ".join(f"{p}: pixels / error / PSNR / gain" for p in PARTS)
        + " |",
        "|---|---|" + "---|" * len(PARTS),
    ]
    for row, f in figures.items():
        cells = [
            f"{100 * f[p]['pixels']:.0f}% / {100 * f[p]['error']:.0f}% / {f[p]['psnr']:.1f} / +{f[p]['gain']:.2f}"
            for p in PARTS
        ]
        lines.append(f"| {row} | {f['psnr']:.2f} / {f['view_mean']:.2f} | " + " | ".join(cells) + " |")
    return lines + [""]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", default="dev", choices=("dev", "dev-b"))
    parser.add_argument("--objects", type=int, default=3)
    parser.add_argument("--model", default="dr")
    parser.add_argument("--radius", type=int, default=2, help="width of the silhouette and edge bands (px)")
    parser.add_argument("--rows", nargs="+", default=list(DEFAULT_ROWS), help="2D=RUN or LABEL=RUN/ASSET")
    parser.add_argument(
        "--fit-to-truth",
        nargs="*",
        default=[],
        metavar="LABEL",
        help="rows whose asset is also shown with its metallic fitted to the true training maps",
    )
    parser.add_argument("--fit-steps", type=int, default=1200, help="steps of that fit (default 1200)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    from benchmarks.generalise import object_set
    from matspray.render.shade.lights import hdri_files

    out = args.out or Path(f"runs/generalise-{args.set}-demo")
    per_object = {}
    for spec in object_set(args.set, args.objects, hdri_files()):
        folder = out / "objects" / spec.name
        per_object[spec.name] = object_rows(
            folder / "data", folder / "runs", args.model, args.rows, args.radius, args.fit_to_truth, args.fit_steps
        )
        print("\n".join(table(spec.name, per_object[spec.name])), flush=True)
    print("\n".join(table(f"mean of {len(per_object)}", mean_figures(list(per_object.values())))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
