"""The one-command demo and the multi-object benchmark.

`run_demo`: make a benchmark object with `matspray synth`, run the full method and its ablations
with the simulated predictor, evaluate against the ground truth and write the report.
`run_bench`: the same over several objects (procedural shapes and seeds, or glTF assets), with the
tables averaged, as the paper averages over 17 objects; a thin loop of "make object -> run object".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from matspray.config import PipelineConfig, build_config
from matspray.errors import SettingError
from matspray.eval.report import write_report
from matspray.eval.run_eval import evaluate_run
from matspray.eval.tables import write_tables
from matspray.gltf.read import read_gltf
from matspray.pipeline import Pipeline
from matspray.rundir import write_json
from matspray.synth import SynthConfig, make_object
from matspray.variants import LABELS, VARIANT_NAMES

SHAPES = ("composite", "blob", "rounded-cube", "torus", "capsule", "sphere")


@dataclass(frozen=True)
class DemoSize:
    res: int
    views: int
    test_views: int
    spp: int


DEMO_SIZES = {
    "test": DemoSize(res=40, views=8, test_views=2, spp=8),
    "demo": DemoSize(res=128, views=40, test_views=10, spp=64),
    "paper": DemoSize(res=512, views=100, test_views=200, spp=256),
}


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


def make_demo_object(out: Path, preset: str, shape: str, seed: int, progress: bool = True, asset: str | None = None,
                     env: str = "sky", relight_envs: list[str] | None = None) -> Path:
    """A `matspray synth` object for `preset` in `out` (reused when it is already there): a procedural `shape`
    or the glTF file `asset`, trained under `env` and relit under `relight_envs` (None: synth's default lights)."""
    size = DEMO_SIZES[preset]
    config = SynthConfig(shape=shape if asset is None else "random", seed=seed, resolution=size.res, train_views=size.views,
                         test_views=size.test_views, spp=size.spp, asset=asset, env=env, relight_envs=relight_envs)
    if not (out / "scene.json").exists():
        make_object(config, out, progress=progress)
    return out


def run_object(data: Path, run_dir: Path, config: PipelineConfig, variants=VARIANT_NAMES, progress: bool = True, log=print) -> dict:
    """Run every variant of the method on one object, evaluate it and write its report (earlier stages are reused)."""
    pipeline = Pipeline(data, run_dir, config, progress=progress, log=log)
    pipeline.run_all(variants)
    metrics = evaluate_run(run_dir, data, progress=progress)
    write_report(run_dir, metrics, data)
    return metrics


def run_demo(out, preset: str = "demo", shape: str = "composite", seed: int = 0, progress: bool = True, log=print,
             config: PipelineConfig | None = None) -> Path:
    """The demo object of `preset` and every variant on it; `config` (default: the preset's matspray
    method with the simulated predictor) chooses the method and its settings."""
    if preset not in DEMO_SIZES:
        raise SettingError("preset", f"unknown preset '{preset}'; choose one of {', '.join(DEMO_SIZES)}")
    out = Path(out)
    data = make_demo_object(out / "data", preset, shape, seed, progress)
    run_object(data, out / "run", config or build_config(preset, predictor="simulated"), progress=progress, log=log)
    return out / "run" / "report.html"


def run_bench(out, objects, preset: str = "demo", progress: bool = True, log=print, config: PipelineConfig | None = None) -> dict:
    """Every object of `objects` (a count of procedural objects, or a list of BenchObject) made and run;
    returns and writes the averaged tables with one row per object (its variants and seconds).
    bench.json is rewritten after each object, so a partial benchmark shows what has finished."""
    specs = procedural_objects(objects) if isinstance(objects, int) else list(objects)
    if not specs:
        raise SettingError("objects", "the benchmark has no objects")
    config = config or build_config(preset, predictor="simulated")
    out = Path(out)
    per_object, rows = [], {}
    for index, spec in enumerate(specs):
        log(f"bench: object {index + 1}/{len(specs)} ({spec.asset or spec.shape}, seed {spec.seed})")
        start = time.perf_counter()
        data = make_demo_object(out / spec.name / "data", preset, spec.shape, spec.seed, progress, asset=spec.asset)
        made = time.perf_counter()
        per_object.append(run_object(data, out / spec.name / "run", config, progress=progress, log=log))
        rows[spec.name] = object_row(spec, per_object[-1], made - start, time.perf_counter() - made)
        log(f"bench: {spec.name}: synth {rows[spec.name]['seconds']['synth']:.1f} s, method {rows[spec.name]['seconds']['method']:.1f} s")
        write_json(out / "bench.json", {"objects": len(specs), "finished": index + 1, "preset": preset, "method": config.method,
                                        "per_object": rows})
    averaged = average_tables(per_object)
    averaged["title"] = f"MatSpray benchmark: {len(specs)} objects, preset {preset}"
    averaged["objects"] = rows
    write_json(out / "bench.json", {"objects": len(specs), "finished": len(specs), "preset": preset, "method": config.method,
                                    "per_object": rows, "tables": averaged})
    write_tables(out / "tables.md", averaged)
    return averaged


def object_row(spec: BenchObject, metrics: dict, synth_seconds: float, method_seconds: float) -> dict:
    """One object's line of the benchmark: relighting and base colour PSNR per variant, and its seconds."""
    variants = metrics.get("variants", {})
    psnr = {row: {LABELS[v]: variants[v]["summary"][row]["psnr"] for v in variants if row in variants[v]["summary"]}
            for row in ("relighting", "basecolor")}
    return {"source": spec.asset or f"{spec.shape} (seed {spec.seed})", "psnr": psnr,
            "seconds": {"synth": synth_seconds, "method": method_seconds}}


def _mean(values):
    values = [v for v in values if v is not None]
    if not values:
        return None
    return math.fsum(values) / len(values)


def average_tables(metrics: list[dict]) -> dict:
    """Average the per-object table entries; metallic PSNR follows the paper's infinity rule
    (objects with infinite PSNR are counted and left out of the mean)."""
    out: dict = {"notes": sorted({n for m in metrics for n in m.get("notes", [])}), "lpips": metrics[0].get("lpips")}
    for key in ("table2", "softmax"):
        names = {name for m in metrics for name in m.get(key, {})}
        out[key] = {name: {metric: _mean([m[key][name].get(metric) for m in metrics if name in m.get(key, {})]) for metric in ("psnr", "ssim", "lpips")} for name in names}
    table1 = {}
    for method in {name for m in metrics for name in m.get("table1", {})}:
        rows = {}
        for row in {r for m in metrics for r in m.get("table1", {}).get(method, {})}:
            entries = [m["table1"][method][row] for m in metrics if row in m.get("table1", {}).get(method, {})]
            if row == "metallic":
                finite = [e["psnr"] for e in entries if e.get("psnr") is not None and math.isfinite(e["psnr"])]
                rows[row] = {"psnr": _mean(finite) if finite else math.inf, "ssim": _mean([e.get("ssim") for e in entries]),
                             "lpips": _mean([e.get("lpips") for e in entries]), "psnr_infinite": len(entries) - len(finite), "objects": len(entries)}
            else:
                rows[row] = {metric: _mean([e.get(metric) for e in entries]) for metric in ("psnr", "ssim", "lpips")}
        table1[method] = rows
    out["table1"] = table1
    stages = {stage for m in metrics for column in m.get("timings", {}).values() for stage in column}
    out["timings"] = {"Ours (mean per object)": {s: _mean([c.get(s) for m in metrics for c in m.get("timings", {}).values()]) for s in stages}}
    return out
