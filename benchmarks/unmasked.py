"""An unmasked capture end to end, against the same capture run with its true masks.

    python -m benchmarks.unmasked [--preset demo|test] [--shape composite] [--seed 3] [--out runs/unmasked]
                                  [--object-bounds X,Y,Z,R] [--captures unmasked masked] [--set KEY=VALUE ...]
                                  [--backdrop env|dark] [--cameras sphere|turntable|front] [--fill 0.92]
                                  [--tabletop grey|white-on-dark|dark-on-light]

Makes a `matspray synth` object whose photos show the training light behind it and a ground plane under
it (`--background env --ground`: RGB photos, no masks), at the preset's size, and a copy of it whose
photos carry the true masks as alpha (the same pixels otherwise). Runs the full method on both
(`matspray run`, simulated predictor). The unmasked run makes its own masks from its geometry (the
`masks` stage). Prints, for each: the geometry's test PSNR on the held-out photos (whole image for the
unmasked capture, object for the masked one), the masks' IoU against the true masks of the test views
(unmasked only), the relighting PSNR under the held-out lights against Mitsuba's truth, and seconds.
Targets: IoU >= 0.9, relighting within 1.5 dB of the masked run. `--captures unmasked` runs the
unmasked capture alone; `--set` passes settings to its run (`matspray run --set`), e.g.
`geometry.focus_from=0` for the geometry without object focus. `--backdrop dark` shows nothing behind the object
and its ground (a table-top capture before black cloth, DTU-style); `--cameras turntable` puts every view on one ring;
`--cameras front --fill 1.1 --tabletop white-on-dark` makes the one-sided capture of an object filling the frame.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from matspray.batch.demo import DEMO_SIZES
from matspray.cli.settings import settings_from_overrides
from matspray.data import load_scene
from matspray.data.images import write_image
from matspray.eval.run_eval import evaluate_run
from matspray.method.config import build_config
from matspray.method.pipeline import Pipeline
from matspray.predictors.ground_truth import read_ground_truth_coverage
from matspray.synth import SynthConfig, make_object

BACKDROPS = {"env": "env", "dark": "transparent"}  # --backdrop -> SynthConfig.background (with the ground: no mask)


def masked_copy(data: Path, out: Path) -> Path:
    """`data` with its photos rewritten as RGBA, alpha = the true mask (the ground truth's coverage)."""
    if (out / "scene.json").exists():
        return out
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(data, partial)
    for view in load_scene(data).views:
        write_image(partial / view.path.relative_to(data), view.image, read_ground_truth_coverage(view))
    partial.rename(out)
    return out


def run_capture(data: Path, run: Path, preset: str, object_bounds, settings: dict | None = None) -> dict:
    config = build_config(preset, predictor="simulated", object_bounds=object_bounds, **(settings or {}))
    start = time.perf_counter()
    Pipeline(data, run, config, progress=False).run_all(("full",))
    seconds = time.perf_counter() - start
    metrics = evaluate_run(run, progress=False)
    geometry = json.loads((run / "geometry" / "metrics.json").read_text())
    return {
        "relight": metrics["variants"]["full"]["summary"]["relighting"]["psnr"],
        "geometry_psnr": geometry["psnr"],
        "geometry_psnr_object": geometry.get("psnr_masked"),
        "iou": metrics.get("masks", {}).get("iou_mean"),
        "iou_min": metrics.get("masks", {}).get("iou_min"),
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=("test", "demo"), default="demo")
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("runs/unmasked"))
    parser.add_argument(
        "--object-bounds", default=None, help="x,y,z,r or x0,y0,z0,x1,y1,z1 for the unmasked run (default: automatic)"
    )
    parser.add_argument("--captures", nargs="+", choices=("unmasked", "masked"), default=["unmasked", "masked"])
    parser.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="settings of the unmasked run")
    parser.add_argument(
        "--backdrop",
        choices=tuple(BACKDROPS),
        default="env",
        help="behind the object on its ground: env (the training light, as outdoors or in a lit room; default) or "
        "dark (nothing: a black backdrop, as a table-top capture before black cloth, DTU-style)",
    )
    parser.add_argument(
        "--cameras",
        choices=("sphere", "turntable", "front"),
        default="sphere",
        help="sphere (views from 10 to 70 degrees up; default), turntable (one ring at 20 degrees) or front (one side "
        "only, up to 45 degrees: the one-sided capture)",
    )
    parser.add_argument("--fill", type=float, default=0.92, help="the object's share of the frame (1.1: fills it)")
    parser.add_argument(
        "--tabletop",
        choices=("grey", "white-on-dark", "dark-on-light"),
        default="grey",
        help="the ground: grey (default) or a textured table with a white object on a dark one or a dark on a light",
    )
    args = parser.parse_args()
    settings = settings_from_overrides(args.set, args.preset)
    size = DEMO_SIZES[args.preset]
    unmasked = args.out / "data-unmasked"
    config = SynthConfig(
        shape=args.shape,
        seed=args.seed,
        resolution=size.res,
        train_views=size.views,
        test_views=size.test_views,
        spp=size.spp,
        background=BACKDROPS[args.backdrop],
        ground=True,
        cameras=args.cameras,
        fill=args.fill,
        tabletop=args.tabletop,
    )
    if not (unmasked / "scene.json").exists():
        make_object(config, unmasked, progress=False)
    elif json.loads((unmasked / "scene.json").read_text()).get("settings") != config.identity():
        raise SystemExit(f"{unmasked} holds another object than these options make: give another --out")
    bounds = None if args.object_bounds is None else tuple(float(v) for v in args.object_bounds.split(","))
    rows = {}
    if "unmasked" in args.captures:
        run = args.out / ("run-unmasked" + "".join(f"-{item}" for item in args.set))
        rows["unmasked (own masks)"] = run_capture(unmasked, run, args.preset, bounds, settings)
    if "masked" in args.captures:
        masked = masked_copy(unmasked, args.out / "data-masked")
        rows["true masks"] = run_capture(masked, args.out / "run-masked", args.preset, None)
    print(
        f"\n{args.shape} seed {args.seed}, preset {args.preset} ({size.res} px, {size.views} views), "
        f"backdrop {args.backdrop} + ground, cameras {args.cameras}"
    )
    print("| capture | geometry test PSNR | mask IoU (mean / min) | relight PSNR | s |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, row in rows.items():
        iou = "-" if row["iou"] is None else f"{row['iou']:.3f} / {row['iou_min']:.3f}"
        geometry = row["geometry_psnr_object"] if row["geometry_psnr_object"] is not None else row["geometry_psnr"]
        print(f"| {name} | {geometry:.2f} | {iou} | {row['relight']:.2f} | {row['seconds']:.0f} |")
    if len(rows) < 2:
        return
    gap = rows["true masks"]["relight"] - rows["unmasked (own masks)"]["relight"]
    print(
        f"relighting: the unmasked run is {gap:.2f} dB below the run with true masks (target: "
        "within 1.5 dB); IoU target >= 0.9"
    )


if __name__ == "__main__":
    main()
