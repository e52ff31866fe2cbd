"""Captures without a point cloud: does a `transforms.json` capture train as well as its COLMAP form?

    python -m benchmarks.no_points --colmap DATASET [--stitch [CAPTURE]] [--out runs/no-points] [--preset demo]
        [--geometry-iterations N] [--refine-iterations N]

With --colmap (a dataset made by `matspray colmap`, e.g. the skull's), its cameras are written once more as a
`transforms.json` without points (OUT/transforms: the images the loader undistorted, pinhole intrinsics per frame,
the same train / test split), and three runs are made:
  colmap              `run --data DATASET`: structure from motion's points start the Gaussians
  transforms          `run --data OUT/transforms --set points.triangulate=off`: random points in the bounds
  transforms+points   `run --data OUT/transforms`: points triangulated at the known cameras (matspray.data.triangulate)
With --stitch, the stitch capture (a transforms.json with lens distortion) without and with triangulated points.
Each run is `matspray run --predictor none` then `matspray eval --run RUN --no-report`, in its own process; the figures
are eval's held-out views (never trained on) scored inside the run's object mask. Finished runs are not redone.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from benchmarks.real_captures import CAPTURES_DIR, command


def write_transforms(dataset: Path, out: Path) -> Path:
    """The COLMAP dataset's views as a nerfstudio capture without points: the undistorted photos at full size, their
    pinhole cameras, and its train / test split as split lists."""
    from matspray.data import load_scene
    from matspray.data.formats.nerfstudio import write_nerfstudio

    if (out / "transforms.json").is_file():
        return out
    scene = load_scene(dataset, downscale=1.0)
    work = out.with_name(out.name + ".tmp")
    write_nerfstudio(work, {"train": scene.train, "test": scene.test})
    work.rename(out)
    return out


def run_form(name: str, data: Path, settings: list[str], args, log: Path) -> dict:
    run = args.out / name
    steps = []
    made = json.loads((run / "no-points.json").read_text()) if (run / "no-points.json").is_file() else {}
    same = made.get("settings") == settings and made.get("object_bounds") == args.object_bounds
    if not (same and (run / "eval" / "heldout.json").exists()):  # `run` reuses the stages the change leaves alone
        set_args = ["--set", *settings] if settings else []
        bounds = [f"--object-bounds={args.object_bounds}"] if args.object_bounds else []  # it may start with a minus
        steps.append(
            command(
                ["run", "--data", str(data), "--out", str(run), "--preset", args.preset, "--predictor", "none"]
                + bounds
                + set_args,
                log,
            )
        )
        steps.append(command(["eval", "--run", str(run), "--no-report"], log))
    from matspray.method.masks import read_object_masks

    metrics = json.loads((run / "eval" / "heldout.json").read_text())
    stage = json.loads((run / "points" / "stage.json").read_text()) if (run / "points").is_dir() else None
    record = {
        "form": name,
        "data": str(data),
        "settings": settings,
        "object_bounds": args.object_bounds,
        "region": read_object_masks(run / "masks").region.describe(),
        "heldout": metrics["heldout"]["summary"],
        "train": metrics["train"]["summary"],
        "mask_coverage": [round(r["mask_coverage"], 3) for r in metrics["heldout"]["per_view"]],
        "triangulated_points": None if stage is None else stage.get("points"),
        "stage_seconds": json.loads((run / "timings.json").read_text()),
        "steps": steps,
    }
    (run / "no-points.json").write_text(json.dumps(record, indent=1))
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--colmap", type=Path, help="a COLMAP dataset made by `matspray colmap` (with its points)")
    parser.add_argument(
        "--stitch",
        nargs="?",
        type=Path,
        const=CAPTURES_DIR / "stitch",
        help="also the stitch capture (default: the shared data's), without and with points",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/no-points"))
    parser.add_argument("--preset", default="demo", choices=("test", "demo", "paper"))
    parser.add_argument("--geometry-iterations", type=int, help="for every run alike (default: the preset's)")
    parser.add_argument("--refine-iterations", type=int, help="for every run alike (default: the preset's)")
    parser.add_argument(
        "--object-bounds",
        help="one object region 'x,y,z,r' (or a box) for every run, so that each is scored inside the same region "
        "(default: each run's automatic one); a rerun with another region reuses the geometry",
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "commands.log"
    common = []
    if args.geometry_iterations:
        common.append(f"geometry.iterations={args.geometry_iterations}")
    if args.refine_iterations:
        common.append(f"refine.iterations={args.refine_iterations}")
    forms = []
    if args.colmap is not None:
        transforms = write_transforms(args.colmap, args.out / "transforms")
        forms += [
            ("colmap", args.colmap, common),
            ("transforms", transforms, common + ["points.triangulate=off"]),
            ("transforms+points", transforms, common),
        ]
    if args.stitch is not None:
        stitch = args.stitch.resolve()
        forms += [("stitch", stitch, common + ["points.triangulate=off"]), ("stitch+points", stitch, common)]
    if not forms:
        raise SystemExit("benchmarks.no_points: give --colmap DATASET and/or --stitch")
    print(
        "| form | held-out PSNR / SSIM, geometry | asset | training PSNR, geometry | triangulated points "
        "| mask coverage | object region |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | --- |")
    for name, data, settings in forms:
        r = run_form(name, data, settings, args, log)
        geometry, train = r["heldout"]["radiance"], r["train"]["radiance"]
        asset = next((v for k, v in r["heldout"].items() if k != "radiance"), None)
        shown = "" if asset is None else f"{asset['psnr']:.2f} / {asset['ssim']:.3f}"
        points = "" if r["triangulated_points"] is None else str(r["triangulated_points"])
        coverage = f"{100 * min(r['mask_coverage']):.1f}-{100 * max(r['mask_coverage']):.1f} %"
        print(
            f"| {name} | {geometry['psnr']:.2f} / {geometry['ssim']:.3f} | {shown} | {train['psnr']:.2f} | {points} "
            f"| {coverage} | {r['region']} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
