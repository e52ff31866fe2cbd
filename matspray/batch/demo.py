"""The one-command demo and the multi-object benchmark.

`run_demo`: make a benchmark object with `matspray synth`, run the full method and its ablations
with the simulated predictor, evaluate against the ground truth and write the report.
`run_bench`: the same over several objects (procedural shapes and seeds, or glTF assets), made first and
then run by `matspray batch`, with the tables averaged, as the paper averages over 17 objects.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from matspray.batch import BatchConfig, run_batch, run_one_object
from matspray.device import resolve_device
from matspray.errors import DataError, SettingError
from matspray.eval.tables import write_tables
from matspray.gltf.read import read_gltf
from matspray.method.config import PipelineConfig, build_config
from matspray.presets import DEMO_SIZES, LABELS, PAPER_VARIANTS
from matspray.render.backend import resolve_backend
from matspray.render.numba.backend import compile_in_background
from matspray.rundir import write_json
from matspray.synth import SynthConfig, make_object

SHAPES = ("composite", "blob", "rounded-cube", "torus", "capsule", "sphere")


ASSET_SUFFIXES = (".glb", ".gltf")


@dataclass(frozen=True)
class BenchObject:
    """One benchmark object: a procedural shape and seed, or a glTF asset (its cameras from the seed)."""

    name: str  # its folder in the benchmark
    shape: str = "composite"
    seed: int = 0
    asset: str | None = None


def procedural_objects(count: int) -> list[BenchObject]:
    """Shapes in turn, seeds 0, 1, ..."""
    if count < 1:
        raise SettingError("objects", f"must be >= 1, got {count}")
    return [BenchObject(f"{i:02d}-{SHAPES[i % len(SHAPES)]}", SHAPES[i % len(SHAPES)], i) for i in range(count)]


def asset_objects(paths) -> list[BenchObject]:
    """One object per .glb/.gltf file given, or found (sorted) in a folder given; seeds 0, 1, ..."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(p for p in path.rglob("*") if p.suffix.lower() in ASSET_SUFFIXES and p.is_file())
            if not found:
                raise SettingError("assets", f"the folder {path} holds no .glb or .gltf file")
            files += found
        elif path.suffix.lower() in ASSET_SUFFIXES and path.is_file():
            files.append(path)
        else:
            raise SettingError("assets", f"{path} is not a .glb/.gltf file or a folder of them")
    return [BenchObject(f"{i:02d}-{f.stem}", "asset", i, str(f)) for i, f in enumerate(files)]


def check_assets(objects: list[BenchObject]) -> None:
    """Read every asset once before the benchmark starts, so a bad file stops it before any work."""
    for spec in objects:
        if spec.asset is not None:
            read_gltf(spec.asset)


def make_demo_object(
    out: Path,
    preset: str,
    shape: str,
    seed: int,
    progress: bool = True,
    asset: str | None = None,
    env: str = "sky",
    relight_envs: list[str] | None = None,
    resolution: int | None = None,
) -> Path:
    """A `matspray synth` object for `preset` in `out` (reused when it is already there): a procedural `shape`
    or the glTF file `asset`, trained under `env` and relit under `relight_envs` (None: synth's default lights),
    rendered at `resolution` px (None: the preset's)."""
    size = DEMO_SIZES[preset]
    config = SynthConfig(
        shape=shape if asset is None else "random",
        seed=seed,
        resolution=resolution or size.res,
        train_views=size.views,
        test_views=size.test_views,
        spp=size.spp,
        asset=asset,
        env=env,
        relight_envs=relight_envs,
    )
    if not (out / "scene.json").exists():
        make_object(config, out, progress=progress)
    return out


def run_object(
    data: Path, run_dir: Path, config: PipelineConfig, variants=PAPER_VARIANTS, progress: bool = True, log=print
) -> dict:
    """Run every variant of the method on one object, evaluate it and write its report (earlier stages are reused)."""
    metrics = run_one_object(data, run_dir, config, variants, progress=progress, log=log)
    if metrics is None:
        raise DataError(f"{data}: no ground truth to evaluate against; make the object with `matspray synth`")
    return metrics


def run_demo(
    out,
    preset: str = "demo",
    shape: str = "composite",
    seed: int = 0,
    progress: bool = True,
    log=print,
    config: PipelineConfig | None = None,
) -> Path:
    """The demo object of `preset` and every variant on it; `config` (default: the preset's matspray
    method with the simulated predictor) chooses the method and its settings."""
    if preset not in DEMO_SIZES:
        raise SettingError("preset", f"unknown preset '{preset}'; choose one of {', '.join(DEMO_SIZES)}")
    out = Path(out)
    config = config or build_config(preset, predictor="simulated")
    if resolve_backend(config.backend, resolve_device(config.device), notify=log) == "numba":
        compile_in_background()  # while the object is rendered (a fresh install compiles the kernels)
    data = make_demo_object(out / "data", preset, shape, seed, progress)
    run_object(data, out / "run", config, progress=progress, log=log)
    return out / "run" / "report.html"


def run_bench(
    out,
    objects,
    preset: str = "demo",
    progress: bool = True,
    log=print,
    config: PipelineConfig | None = None,
    workers: int | None = None,
    use_ray: bool = True,
) -> dict:
    """Every object of `objects` (a count of procedural objects, or a list of BenchObject) made in
    OUT/data/<name>/ and run by `matspray batch` into OUT/<name>/ (`workers` at once); writes the averaged
    tables with one row per object (its variants and seconds) and returns the batch summary."""
    specs = procedural_objects(objects) if isinstance(objects, int) else list(objects)
    if not specs:
        raise SettingError("objects", "the benchmark has no objects")
    config = config or build_config(preset, predictor="simulated")
    out = Path(out)
    datas, synth_seconds = [], {}
    for index, spec in enumerate(specs):
        log(f"bench: object {index + 1}/{len(specs)} ({spec.asset or spec.shape}, seed {spec.seed})")
        start = time.perf_counter()
        datas.append(
            make_demo_object(out / "data" / spec.name, preset, spec.shape, spec.seed, progress, asset=spec.asset)
        )
        synth_seconds[spec.name] = time.perf_counter() - start
    summary = run_batch(
        datas,
        out,
        BatchConfig(pipeline=config, variants=PAPER_VARIANTS, workers=workers, use_ray=use_ray),
        progress=progress,
        log=log,
    )
    averaged = summary["averages"]
    if averaged is not None:
        finished = {row["name"]: row for row in summary["objects"] if row["status"] != "failed"}
        averaged["title"] = f"MatSpray benchmark: {summary['averaged_over']} of {len(specs)} objects, preset {preset}"
        averaged["objects"] = {
            spec.name: object_row(
                spec,
                json.loads((out / spec.name / "eval" / "metrics.json").read_text()),
                synth_seconds[spec.name],
                sum(finished[spec.name]["stage_seconds"].values()),
            )
            for spec in specs
            if spec.name in finished and (out / spec.name / "eval" / "metrics.json").exists()
        }
        write_json(
            out / "bench.json", {"objects": len(specs), "preset": preset, "method": config.method, "tables": averaged}
        )
        write_tables(out / "tables.md", averaged)
    return summary


def object_row(spec: BenchObject, metrics: dict, synth_seconds: float, method_seconds: float) -> dict:
    """One object's line of the benchmark: relighting and base colour PSNR per variant, and its seconds
    (making the object in this call: 0 when made before; the method: its stages, whichever call ran them)."""
    variants = metrics.get("variants", {})
    psnr = {
        row: {LABELS[v]: variants[v]["summary"][row]["psnr"] for v in variants if row in variants[v]["summary"]}
        for row in ("relighting", "basecolor")
    }
    return {
        "source": spec.asset or f"{spec.shape} (seed {spec.seed})",
        "psnr": psnr,
        "seconds": {"synth": synth_seconds, "method": method_seconds},
    }
