"""`run_batch`: many objects, one Ray task each (or one after another in-process without Ray).

Each object runs the ordinary pipeline into `OUT/<object name>/`. A rerun of the same batch skips
the finished objects and resumes an interrupted one through its run folder's stage reuse. An object
that fails is reported with its one-line error and the others go on. `OUT/batch.json` records the
settings that shape the results; another batch's settings in the same folder are refused.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from tqdm import tqdm

from matspray.batch.cluster import INSTALL_HINT, check_reachable, load_ray, ray_session
from matspray.batch.objects import BatchObject, batch_objects, finished_record, object_result, one_line, process_object
from matspray.batch.summary import batch_summary, write_summary
from matspray.errors import ConfigError, RunError, SettingError
from matspray.method.config import PipelineConfig
from matspray.presets import VARIANT_NAMES
from matspray.rundir import fingerprint, read_json, to_plain, write_json

SETTINGS_RECORD = "batch.json"
POLL_S = 0.5


@dataclass(frozen=True)
class BatchConfig:
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)  # every object's run settings
    variants: tuple[str, ...] | None = ("full",)  # None: each run's default (full, or photos-only without 2D maps)
    workers: int | None = None  # objects at once; None: local CPUs // cpus_per_object, or the whole cluster
    address: str | None = None  # an existing Ray cluster ('HOST:PORT', 'ray://HOST:PORT', 'auto'); None: a local Ray
    cpus_per_object: int = 1  # Ray CPUs of one object's task, and its torch threads
    gpus_per_object: float = 0.0
    use_ray: bool = True  # False: one after another in this process even when Ray is installed


def check_config(config: BatchConfig) -> None:
    if config.workers is not None and config.workers < 1:
        raise SettingError("workers", f"must be >= 1, got {config.workers}")
    if config.cpus_per_object < 1:
        raise SettingError("cpus_per_object", f"must be >= 1, got {config.cpus_per_object}")
    if not (math.isfinite(config.gpus_per_object) and config.gpus_per_object >= 0):
        raise SettingError("gpus_per_object", f"must be a finite number >= 0, got {config.gpus_per_object:g}")
    unknown = [v for v in config.variants or () if v not in VARIANT_NAMES]
    if unknown or config.variants == ():
        raise SettingError(
            "variants", f"unknown variant '{(unknown or [''])[0]}'; choose from {', '.join(VARIANT_NAMES)}"
        )


def batch_settings(config: BatchConfig) -> dict:
    """What shapes the results (not how many machines make them)."""
    return {
        "pipeline": to_plain(config.pipeline),
        "variants": None if config.variants is None else list(config.variants),
    }


_ABSENT = object()  # a setting one record lacks


def _differences(old, new, prefix: str = "") -> list[str]:
    """The settings that differ, as 'name new here, old there'. A setting one side lacks counts as equal
    when the other side leaves it unset (None): it was added (or dropped) since, at its neutral default."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [
            d
            for key in sorted(set(old) | set(new))
            for d in _differences(old.get(key, _ABSENT), new.get(key, _ABSENT), f"{prefix}{key}.")
        ]
    if old == new or (old is _ABSENT and new is None) or (new is _ABSENT and old is None):
        return []
    return [f"{prefix.rstrip('.')} {_shown(new)} here, {_shown(old)} there"]


def _shown(value) -> str:
    return "absent" if value is _ABSENT else repr(value)


def claim_batch_folder(out: Path, settings: dict) -> None:
    """Record the batch's settings in `out`, or refuse a folder that holds another batch's."""
    record = out / SETTINGS_RECORD
    if record.exists():
        changes = _differences(read_json(record).get("settings") or {}, settings)
        if changes:
            raise RunError(
                f"{out}: holds a batch made with other settings ({'; '.join(changes[:3])}); use another output "
                "folder, or the same settings to finish that batch"
            )
    write_json(record, {"settings": settings, "fingerprint": fingerprint(settings)})


class StageBoard:
    """The current stage of each running object (a Ray actor under Ray)."""

    def __init__(self):
        self.stages: dict[str, str] = {}

    def update(self, name: str, stage: str | None) -> None:
        if stage is None:
            self.stages.pop(name, None)
        else:
            self.stages[name] = stage

    def snapshot(self) -> dict[str, str]:
        return dict(self.stages)


def _show(bar, stages: dict[str, str]) -> None:
    bar.set_postfix_str(", ".join(f"{name}: {stage}" for name, stage in sorted(stages.items()))[:120], refresh=True)


def _ray_task(obj: BatchObject, config: PipelineConfig, variants, settings_fp: str, threads: int, board) -> dict:
    """The body of one object's Ray task. A task Ray gave no GPU runs on the CPU even where the
    machine has one (device auto), so that only scheduled tasks share a GPU."""
    import ray

    if config.device == "auto" and not ray.get_gpu_ids():
        config = replace(config, device="cpu")
    result = process_object(
        obj, config, variants, settings_fp, threads, lambda stage: board.update.remote(obj.name, stage)
    )
    board.update.remote(obj.name, None)
    return result


def progress_bar(total: int, progress: bool):
    return tqdm(total=total, desc="batch", unit="object", disable=not progress)


def run_serial(objects, config: BatchConfig, settings_fp: str, progress: bool) -> list[dict]:
    board = StageBoard()
    results = []
    with progress_bar(len(objects), progress) as bar:
        for obj in objects:

            def stage(name, obj=obj):
                board.update(obj.name, name)
                _show(bar, board.snapshot())

            results.append(
                process_object(obj, config.pipeline, config.variants, settings_fp, config.cpus_per_object, stage)
            )
            board.update(obj.name, None)
            bar.update(1)
    return results


def run_ray(ray, objects, config: BatchConfig, settings_fp: str, workers: int | None, progress: bool) -> list[dict]:
    """One task per object, at most `workers` in flight; a task that dies (killed for memory, a lost
    node) fails its object alone."""
    task = ray.remote(_ray_task).options(
        num_cpus=config.cpus_per_object, num_gpus=config.gpus_per_object, max_retries=0
    )
    board = ray.remote(StageBoard).options(num_cpus=0).remote()
    queue, pending, results = list(objects), {}, {}
    bar = progress_bar(len(objects), progress)
    try:
        while queue or pending:
            while queue and (workers is None or len(pending) < workers):
                obj = queue.pop(0)
                pending[
                    task.remote(obj, config.pipeline, config.variants, settings_fp, config.cpus_per_object, board)
                ] = obj
            done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
            for ref in done:
                obj = pending.pop(ref)
                try:
                    results[obj.name] = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    results[obj.name] = object_result(
                        obj, "failed", one_line(exc.cause if getattr(exc, "cause", None) else exc)
                    )
                bar.update(1)
            _show(bar, ray.get(board.snapshot.remote()))
    finally:
        bar.close()
        for ref in pending:
            ray.cancel(ref, force=True)
    return [results[obj.name] for obj in objects]


def local_cpus() -> int:
    """CPU cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def run_objects(ray, objects, config: BatchConfig, settings_fp: str, progress: bool, log) -> tuple[list[dict], str]:
    """The objects' results, and the engine that made them in words."""
    if not objects:
        return [], "none (every object finished before)"
    if ray is None:
        why = f"Ray is not installed ({INSTALL_HINT})" if config.use_ray else "Ray is not used"
        log(f"batch: {why}; running the {len(objects)} objects one after another in this process")
        return run_serial(objects, config, settings_fp, progress), "in-process, one object after another"
    workers = config.workers or (None if config.address else max(1, local_cpus() // config.cpus_per_object))
    engine = (
        f"Ray {'at ' + config.address if config.address else 'local'}, "
        + (f"{workers} workers" if workers else "as many workers as the cluster holds")
        + f", {config.cpus_per_object} CPU(s)"
        + (f" and {config.gpus_per_object:g} GPU(s)" if config.gpus_per_object else "")
        + " per object"
    )
    with ray_session(
        ray, config.address, (workers or 1) * config.cpus_per_object, config.cpus_per_object, config.gpus_per_object
    ):
        log(f"batch: {len(objects)} objects on {engine}")
        return run_ray(ray, objects, config, settings_fp, workers, progress), engine


def run_batch(datas, out, config: BatchConfig, progress: bool = True, log=print) -> dict:
    """Run every dataset of `datas` into `out/<name>/`, write summary.json and summary.md, and
    return the summary (its `failed` lists the objects that failed, with their errors)."""
    check_config(config)
    out = Path(out)
    objects = batch_objects(datas, out)
    if not objects:
        raise ConfigError("no datasets given")
    ray = load_ray() if config.use_ray else None
    if config.address is not None and ray is None:
        raise ConfigError(f"joining the Ray cluster at '{config.address}' needs Ray: {INSTALL_HINT}")
    if ray is not None and config.address not in (None, "auto") and not ray.is_initialized():
        check_reachable(config.address)  # before anything is written or started
    settings = batch_settings(config)
    out.mkdir(parents=True, exist_ok=True)
    claim_batch_folder(out, settings)
    settings_fp = fingerprint(settings)
    start = time.perf_counter()
    finished = {obj.name for obj in objects if finished_record(obj, settings_fp) is not None}
    todo = [obj for obj in objects if obj.name not in finished]
    if finished:
        log(f"batch: {len(finished)} of {len(objects)} objects finished before, skipped: {', '.join(sorted(finished))}")
    results, engine = run_objects(ray, todo, config, settings_fp, progress, log)
    results = {r["name"]: r for r in results}
    results = [results[obj.name] if obj.name in results else object_result(obj, "skipped") for obj in objects]
    summary = batch_summary(results, settings, engine, time.perf_counter() - start)
    write_summary(out, summary)
    return summary
