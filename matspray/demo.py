"""The one-command demo and the multi-object benchmark.

`run_demo`: make a benchmark object with `matspray synth`, run the full method and its ablations
with the simulated predictor, evaluate against the ground truth and write the report.
`run_bench`: the same over several objects (shapes and seeds) through `matspray batch`, with the
tables averaged, as the paper averages over 17 objects.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matspray.batch import BatchConfig, run_batch, run_one_object
from matspray.config import PipelineConfig, build_config
from matspray.errors import DataError, SettingError
from matspray.eval.tables import write_tables
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
    metrics = run_one_object(data, run_dir, config, variants, progress=progress, log=log)
    if metrics is None:
        raise DataError(f"{data}: no ground truth to evaluate against; make the object with `matspray synth`")
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


def run_bench(out, objects: int, preset: str = "demo", progress: bool = True, log=print, config: PipelineConfig | None = None,
              workers: int | None = None, use_ray: bool = True) -> dict:
    """Several objects (shapes in turn, seeds 0, 1, ...) made in OUT/data/ and run by `matspray batch`
    into OUT/<object>/ (`workers` at once); writes the averaged tables and returns the batch summary."""
    if objects < 1:
        raise SettingError("objects", f"must be >= 1, got {objects}")
    config = config or build_config(preset, predictor="simulated")
    out = Path(out)
    datas = []
    for index in range(objects):
        shape = SHAPES[index % len(SHAPES)]
        log(f"bench: object {index + 1}/{objects} ({shape}, seed {index})")
        datas.append(make_demo_object(out / "data" / f"{index:02d}-{shape}", preset, shape, index, progress))
    summary = run_batch(datas, out, BatchConfig(pipeline=config, variants=VARIANT_NAMES, workers=workers, use_ray=use_ray),
                        progress=progress, log=log)
    averaged = summary["averages"]
    if averaged is not None:
        averaged["title"] = f"MatSpray benchmark: {summary['averaged_over']} of {objects} objects, preset {preset}"
        write_json(out / "bench.json", {"objects": objects, "preset": preset, "method": config.method, "tables": averaged})
        write_tables(out / "tables.md", averaged)
    return summary
