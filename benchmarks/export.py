"""The exported mesh against the Gaussian asset it came from, on finished runs of `matspray synth` objects.

    python -m benchmarks.export RUN [RUN ...] --out DIR [--faces 200000] [--texture-size 1024] [--grid 128]
        [--silhouette-rounds 2] [--asset-normals 0.5] [--bake auto]

For each run: `matspray export` in a child process (wall seconds and its peak resident memory, from
the kernel's accounting of that process), then `matspray eval --glb` (Mitsuba renders the mesh under
the held-out lights at the test cameras). Prints one row per run: faces, texture size, export
seconds, peak MiB, relighting PSNR of the Gaussian asset and of the mesh (both against Mitsuba's
truth) and the gap; base colour PSNR of both. Each figure twice: over the true object mask (GT), and over the
object + silhouette (the union of each render's own alpha and the true mask), which counts what a render gets
wrong at and outside the silhouette."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from matspray.eval.glb import evaluate_glb
from matspray.export.config import ExportConfig

DEFAULTS = ExportConfig()


def export_in_child(run: Path, out: Path, args) -> tuple[float, float]:  # -> seconds, peak MiB
    command = [
        sys.executable,
        "-m",
        "matspray",
        "export",
        "--run",
        str(run),
        "--out",
        str(out),
        "--faces",
        str(args.faces),
        "--texture-size",
        str(args.texture_size),
        "--grid",
        str(args.grid),
        "--asset-normals",
        str(args.asset_normals),
        "--silhouette-rounds",
        str(args.silhouette_rounds),
        "--bake",
        args.bake,
        "--backend",
        args.backend,
    ]
    start = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    _, status, usage = os.wait4(child.pid, 0)
    seconds = time.perf_counter() - start
    printed = child.stdout.read()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"export of {run} failed: {printed}")
    print(printed.strip().splitlines()[0], flush=True)
    return seconds, usage.ru_maxrss / 1024  # Linux reports KiB


def run_name(run: Path) -> str:
    """A short name for a run folder: the object's folder for OBJECT/run and OBJECT/runs/CONFIG (the
    generalisation layout, where every object's run folder has the same name), else the folder itself."""
    if run.name == "run":
        return run.parent.name
    if run.parent.name == "runs":
        return f"{run.parent.parent.name}-{run.name}"
    return run.name


def figure(eval_dir: Path, view: str, envs: list[str], path: Path, scale: int = 2) -> None:
    """One picture from an eval --glb report: rows = lights, columns = truth, Gaussians, mesh (grey background)."""
    from PIL import Image

    names = [
        [eval_dir / "report" / f"{view}_{env}_{who}.png" for who in ("truth", "gaussians", "mesh")] for env in envs
    ]
    width, height = Image.open(names[0][0]).size
    sheet = Image.new("RGBA", (3 * width, len(envs) * height), (128, 128, 128, 255))
    for row, files in enumerate(names):
        for column, name in enumerate(files):
            image = Image.open(name).convert("RGBA")
            sheet.paste(image, (column * width, row * height), image)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.resize((3 * width * scale, len(envs) * height * scale), Image.LANCZOS).convert("RGB").save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--faces", type=int, default=DEFAULTS.faces)
    parser.add_argument("--texture-size", type=int, default=DEFAULTS.texture_size)
    parser.add_argument("--grid", type=int, default=DEFAULTS.grid)
    parser.add_argument("--asset-normals", type=float, default=DEFAULTS.asset_normals)
    parser.add_argument("--silhouette-rounds", type=int, default=DEFAULTS.silhouette_rounds)
    parser.add_argument("--bake", default=DEFAULTS.bake)
    parser.add_argument(
        "--backend",
        default="torch",
        help="rasterizer of the export's depth renders (default torch: the reference; "
        "the Gaussians' eval renders use torch too)",
    )
    parser.add_argument(
        "--figure",
        type=Path,
        help="also write the first run's first test view as a PNG: truth | Gaussians | mesh, one row per light",
    )
    args = parser.parse_args()
    rows = []
    for run in args.runs:
        name = run_name(run)
        glb = args.out / f"{name}.glb"
        seconds, peak = export_in_child(run, glb, args)
        metrics = evaluate_glb(glb, run=run, progress=False)
        mesh, gaussians = metrics["mesh"]["summary"], metrics["gaussians"]["summary"]
        for region, suffix in (("GT mask", ""), ("union", "_union")):
            relit, base = f"relighting{suffix}", f"basecolor{suffix}"
            gap = gaussians[relit]["psnr"] - mesh[relit]["psnr"]
            rows.append(
                f"| {name} | {region} | {metrics['faces']} | {args.texture_size} | {seconds:.1f} | {peak:.0f} | "
                f"{gaussians[relit]['psnr']:.2f} | "
                f"{mesh[relit]['psnr']:.2f} | {gap:+.2f} | {gaussians[base]['psnr']:.2f} | {mesh[base]['psnr']:.2f} |"
            )
            print(rows[-1], flush=True)
        if args.figure is not None and run == args.runs[0]:
            figure(
                glb.with_name(f"{glb.stem}_eval"),
                metrics["mesh"]["per_view"][0]["view"],
                metrics["relight_envs"],
                args.figure,
            )
    print(
        "\n| object | region | faces | texture | export s | peak MiB | relight PSNR Gaussians | relight PSNR mesh | "
        "gap dB | base colour PSNR Gaussians | mesh |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
