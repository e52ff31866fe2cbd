"""The one-command demo and the multi-object benchmark.

`run_demo`: make a benchmark object with `matspray synth`, run the full method and its ablations
with the simulated predictor, evaluate against the ground truth and write the report.
`run_bench`: the same over several objects (shapes and seeds), with the tables averaged, as the
paper averages over 17 objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from matspray.config import PipelineConfig, build_config
from matspray.errors import SettingError
from matspray.eval.report import write_report
from matspray.eval.run_eval import evaluate_run
from matspray.eval.tables import write_tables
from matspray.pipeline import Pipeline
from matspray.rundir import write_json
from matspray.synth import SynthConfig, make_object
from matspray.variants import VARIANT_NAMES

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


def make_demo_object(out: Path, preset: str, shape: str, seed: int, progress: bool = True, env: str = "sky",
                     relight_envs: list[str] | None = None) -> Path:
    """A `matspray synth` object for `preset` in `out` (reused when it is already there), trained under
    `env` and relit under `relight_envs` (None: synth's default lights)."""
    size = DEMO_SIZES[preset]
    config = SynthConfig(shape=shape, seed=seed, resolution=size.res, train_views=size.views, test_views=size.test_views, spp=size.spp,
                         env=env, relight_envs=relight_envs)
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


def run_bench(out, objects: int, preset: str = "demo", progress: bool = True, log=print, config: PipelineConfig | None = None) -> dict:
    """Several objects (shapes in turn, seeds 0, 1, ...); returns and writes the averaged tables."""
    if objects < 1:
        raise SettingError("objects", f"must be >= 1, got {objects}")
    config = config or build_config(preset, predictor="simulated")
    out = Path(out)
    per_object = []
    for index in range(objects):
        shape = SHAPES[index % len(SHAPES)]
        name = f"{index:02d}-{shape}"
        log(f"bench: object {index + 1}/{objects} ({shape}, seed {index})")
        data = make_demo_object(out / name / "data", preset, shape, index, progress)
        per_object.append(run_object(data, out / name / "run", config, progress=progress, log=log))
    averaged = average_tables(per_object)
    averaged["title"] = f"MatSpray benchmark: {objects} objects, preset {preset}"
    write_json(out / "bench.json", {"objects": objects, "preset": preset, "method": config.method, "tables": averaged})
    write_tables(out / "tables.md", averaged)
    return averaged


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
