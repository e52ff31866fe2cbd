"""Both real captures of the shared data through the whole method, as a user runs them.

    python -m benchmarks.real_captures [--captures skull stitch] [--preset demo] [--out runs/real-captures]
        [--lights studio sunset forest] [--geometry-iterations N] [--refine-iterations N] [--backend auto]
        [--compare-with ROOT] [--user-asset-only]

Per capture, the `matspray` commands a user types, each in its own process:
  skull   `matspray colmap` on its 66 photos (no poses), then `run` on the dataset it made
  stitch  `run` on its transforms.json (poses with lens distortion, cluttered room)
then `relight` under each light (the held-out test cameras) and once as a turntable (orbit MP4 over the light),
`export` (RUN/export/NAME.glb, which the report and `matspray view` find), and `eval` (held-out photos scored inside the
object mask; report.html with the photo credit). Neither capture has 2D material maps here (no diffusion weights), so
the run makes the user's asset without maps (photos-only), which relight and export take, and beside it the paper's
no-prior baseline, so that the evaluation scores both on the same geometry (`--user-asset-only` leaves the baseline
out). Each capture's summary goes to RESULTS/real-captures-NAME.json, or real-captures-NAME-PRESET.json at another
preset than demo.

Prints per capture: photos registered and mean reprojection error (skull), held-out novel-view PSNR / SSIM /
LPIPS inside the object mask on views never trained on, the share of each held-out view the mask covers,
Gaussians (geometry and asset), seconds per stage and per command, the peak memory of each command, and the
exported mesh's bounding box against the object region. Finished commands are not redone on a rerun (each
one's outputs are checked); delete OUT/<capture> to start over.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from matspray.presets import BASELINE, MAPLESS_DEFAULT, PRESETS

CAPTURES_DIR = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "captures"
SKULL_CREDIT = (
    '"Photogrammetry Test Set: Skull - Cameramoves - Flash - No Background" by alansartlog '
    "(photogrammetry-test-sets), CC BY 4.0"
)
CREDITS = {"skull": SKULL_CREDIT, "stitch": "toy figure video frames from a public TensoRF user-data repository (MIT)"}
VARIANT = MAPLESS_DEFAULT  # what a user's run without maps makes, relights and exports
VARIANTS = [VARIANT, BASELINE]  # and the paper's baseline beside it, scored by the same evaluation


def command(args: list[str], log: Path) -> dict:
    """Run `matspray ARGS` in its own process (output appended to `log`); its seconds and peak resident memory."""
    start = time.perf_counter()
    with open(log, "a") as out:
        out.write(f"\n$ matspray {' '.join(args)}\n")
        out.flush()
        process = subprocess.Popen([sys.executable, "-m", "matspray", *args], stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)  # wait4: this child's own peak memory (ru_maxrss, KiB on Linux)
        process.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - start
    if process.returncode != 0:
        raise SystemExit(f"matspray {' '.join(args)} failed (exit {process.returncode}); see {log}")
    return {
        "command": "matspray " + " ".join(args),
        "seconds": round(seconds, 1),
        "peak_mib": round(usage.ru_maxrss / 1024),
    }


def skull_dataset(out: Path, log: Path, steps: list) -> tuple[Path, dict]:
    dataset = out / "dataset"
    if not (dataset / "sparse" / "0").is_dir():
        steps.append(
            command(
                ["colmap", str(CAPTURES_DIR / "skull" / "images"), "--out", str(dataset), "--single-camera", "--quiet"],
                log,
            )
        )
    import pycolmap

    model = pycolmap.Reconstruction(str(dataset / "sparse" / "0"))
    photos = len(list((CAPTURES_DIR / "skull" / "images").glob("*.JPG")))
    return dataset, {
        "photos": photos,
        "registered": model.num_reg_images(),
        "reprojection_px": round(float(model.compute_mean_reprojection_error()), 3),
        "points": model.num_points3D(),
    }


def run_capture(name: str, args, out_root: Path) -> dict:
    out = out_root / name
    out.mkdir(parents=True, exist_ok=True)
    log = out / "commands.log"
    steps: list[dict] = []
    sfm = None
    if name == "skull":
        data, sfm = skull_dataset(out, log, steps)
    else:
        data = CAPTURES_DIR / name
    run = out / "run"
    compute = ["--backend", args.backend]
    before = args.compare_with / name / "run" if args.compare_with else None
    compare = [str(before)] if before is not None and before.is_dir() else []
    variants = ["--variant", *([VARIANT] if args.user_asset_only else VARIANTS)]
    if not (run / "eval" / "heldout.json").exists():
        named = {"geometry.iterations": args.geometry_iterations, "refine.iterations": args.refine_iterations}
        extra = [f"{key}={value}" for key, value in named.items() if value]
        extra = ["--set", *extra] if extra else []
        steps.append(
            command(
                ["run", "--data", str(data), "--out", str(run), "--preset", args.preset, *variants, *extra, *compute],
                log,
            )
        )
        relight = ["relight", "--run", str(run), "--variant", VARIANT, *compute]
        for light in args.lights:
            steps.append(command([*relight, "--env", light, "--out", str(out / "relit")], log))
        turntable = ["--views", "orbit", "--background", "env", "--out", str(out / "turntable")]
        steps.append(command([*relight, "--env", args.lights[0], *turntable], log))
        steps.append(
            command(
                [
                    "export",
                    "--run",
                    str(run),
                    "--variant",
                    VARIANT,
                    "--out",
                    str(run / "export" / f"{name}.glb"),
                    "--frame",
                    "dataset",
                    *compute,
                ],
                log,
            )
        )
        steps.append(eval_command(run, name, args, compare, compute, log))
    elif compare and not (run / "report" / f"compare_{compare_view(run)}_{args.lights[0]}.png").exists():
        steps.append(eval_command(run, name, args, compare, compute, log))  # the report again, with the comparison
    return summarise(name, out, run, sfm, steps)


def eval_command(run: Path, name: str, args, compare: list[str], compute: list[str], log: Path) -> dict:
    """`matspray eval` of the run: held-out photos scored, report.html with the credit (and `--compare` runs)."""
    flags = ["--compare", *compare] if compare else []
    return command(["eval", "--run", str(run), "--credit", CREDITS[name], "--env", *args.lights, *flags, *compute], log)


def compare_view(run: Path) -> str:
    """The first held-out view's name (the first row of the report's comparison), from the run's dataset record."""
    from matspray.rundir import RunDir

    dataset = RunDir(run).require().dataset()
    return (dataset.get("test_views") or dataset["train_views"])[0]


def summarise(name: str, out: Path, run: Path, sfm: dict | None, steps: list[dict]) -> dict:
    from matspray.data.crop import read_crop_plan
    from matspray.export.frames import glb_box
    from matspray.geometry.ply import read_ply
    from matspray.method.asset import read_asset
    from matspray.method.masks import read_object_masks
    from matspray.rundir import RunDir

    asset = read_asset(RunDir(run).asset_path(VARIANT))
    metrics = json.loads((run / "eval" / "heldout.json").read_text())
    timings = json.loads((run / "timings.json").read_text())
    region = read_object_masks(run / "masks").region
    plan = read_crop_plan(run / "crop")  # None: the photos were used whole
    glb = run / "export" / f"{name}.glb"
    record = {
        "capture": name,
        "sfm": sfm,
        "steps": steps,
        "stage_seconds": timings,
        "gaussians_geometry": len(read_ply(run / "geometry" / "gaussians.ply")[0]),
        "gaussians_asset": len(asset.gaussians),
        "heldout": metrics["heldout"]["summary"],
        "train": metrics["train"]["summary"],
        "mask_coverage": [(r["view"], round(r["mask_coverage"], 3)) for r in metrics["heldout"]["per_view"]],
        "region": region.describe(),
        "glb_box": [[round(v, 3) for v in corner] for corner in glb_box(glb)] if glb.exists() else None,
        "crop_gain": None if plan is None else round(1.0 / plan.mean_side(), 2),  # pixels across the object, x
        "camera_light": flash_record(asset.camera_light),
    }
    (out / "summary.json").write_text(json.dumps(record, indent=1))
    return record


def flash_record(light) -> dict | None:
    """The flash the user's asset learned beside its light (a `CameraLight`: `refine.camera_light`), or None."""
    if light is None:
        return None
    return {"intensity": [round(float(x), 4) for x in light.intensity], "reference_distance": light.reference_distance}


def print_record(record: dict) -> None:
    print(f"\n== {record['capture']} ==")
    if record["sfm"]:
        s = record["sfm"]
        print(
            f"structure from motion: {s['registered']} of {s['photos']} photos registered, mean reprojection error "
            f"{s['reprojection_px']:.3f} px, {s['points']} points"
        )
    for key, value in record["heldout"].items():
        lpips = "n/a" if value["lpips"] is None else f"{value['lpips']:.3f}"
        label = "geometry (3DGS colours)" if key == "radiance" else f"{key} asset under its estimated light"
        print(
            f"held-out, inside the object mask, {label}: PSNR {value['psnr']:.2f} dB, "
            f"SSIM {value['ssim']:.3f}, LPIPS {lpips}"
            f"   (training views: {record['train'][key]['psnr']:.2f} dB)"
        )
    print(
        "mask coverage of each held-out view: "
        + ", ".join(f"{view} {100 * c:.1f}%" for view, c in record["mask_coverage"])
    )
    print(f"Gaussians: {record['gaussians_geometry']} in the geometry, {record['gaussians_asset']} in the asset")
    print(f"object region: {record['region']}")
    gain = record.get("crop_gain")
    print("photos: " + (f"cut to the object, {gain:.2f}x the pixels across" if gain else "used whole"))
    if record["glb_box"]:
        print(f"exported glb box (dataset frame): {record['glb_box'][0]} .. {record['glb_box'][1]}")
    print("seconds per stage: " + ", ".join(f"{k} {v:.0f}" for k, v in record["stage_seconds"].items()))
    for step in record["steps"]:
        print(f"  {step['seconds']:7.1f} s  peak {step['peak_mib']:6d} MiB  {step['command']}")
    if record["steps"]:
        print(f"total: {sum(s['seconds'] for s in record['steps']) / 60:.1f} min")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", nargs="+", choices=("skull", "stitch"), default=["skull", "stitch"])
    parser.add_argument("--preset", default="demo", choices=PRESETS)
    parser.add_argument(
        "--user-asset-only",
        action="store_true",
        help=f"refine only the user's asset ({VARIANT}), not the paper's {BASELINE} baseline beside it",
    )
    parser.add_argument(
        "--out", type=Path, help="folder of the captures' datasets and runs (default runs/real-captures)"
    )
    parser.add_argument(
        "--results-dir",
        type=Path,
        help="where each capture's summary is copied as real-captures-NAME.json, "
        "the files the docs' tables are made from (python -m benchmarks.tables); default docs/results "
        "when --out is left at its default, else nowhere",
    )
    parser.add_argument("--lights", nargs="+", default=["studio", "sunset", "forest"])
    parser.add_argument("--geometry-iterations", type=int)
    parser.add_argument("--refine-iterations", type=int)
    parser.add_argument("--backend", default="auto")
    parser.add_argument(
        "--compare-with",
        type=Path,
        metavar="ROOT",
        help="an earlier --out of this benchmark (before a change, say): each capture's report shows ROOT/NAME/run's "
        "asset beside this run's, relit and cut to the same square around the object (`matspray eval --compare`)",
    )
    args = parser.parse_args()
    if args.results_dir is None and args.out is None:
        args.results_dir = Path("docs/results")
    args.out = args.out or Path("runs/real-captures")
    if not CAPTURES_DIR.is_dir():
        raise SystemExit(f"{CAPTURES_DIR}: the shared captures are not here")
    for name in args.captures:
        record = run_capture(name, args, args.out)
        print_record(record)
        if args.results_dir is not None:
            args.results_dir.mkdir(parents=True, exist_ok=True)
            path = args.results_dir / results_name(name, args.preset)
            path.write_text(json.dumps({**record, "preset": args.preset}, indent=1))
            print(f"results: {path}")


def results_name(capture: str, preset: str) -> str:
    """The results file of a capture at a preset (the demo preset's keeps its first name)."""
    return f"real-captures-{capture}.json" if preset == "demo" else f"real-captures-{capture}-{preset}.json"


if __name__ == "__main__":
    main()
