"""One object of a batch: its name, its run folder, the ordinary pipeline into it, and its record.

`run_one_object` is the per-object work (pipeline, evaluation and report where ground truth exists);
`process_object` wraps it for a batch: threads, stage reports, failure capture and the record of a
finished object (`RUN/batch-object.json`) that lets a rerun skip it.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from matspray.errors import ConfigError, DataError, MatsprayError
from matspray.eval.report import write_report
from matspray.eval.run_eval import check_synthetic, evaluate_run
from matspray.method.config import PipelineConfig
from matspray.method.pipeline import Pipeline
from matspray.presets import variants_for_maps
from matspray.rundir import read_json, write_json

OBJECT_RECORD = "batch-object.json"
OBJECT_LOG = "batch.log"
STAGE_PREFIXES = ("predict", "geometry", "lift", "visibility", "refine")


@dataclass(frozen=True)
class BatchObject:
    name: str
    data: Path  # the dataset folder, resolved
    run: Path  # DIR/<name>/


def batch_objects(datas, out) -> list[BatchObject]:
    """One object per dataset folder, named after the folder; two folders with one name are refused."""
    objects, seen = [], {}
    for data in datas:
        data = Path(data).resolve()
        name = data.name
        if name in seen:
            raise ConfigError(
                f"two datasets are named '{name}': {seen[name]} and {data}; each object's run folder is "
                f"OUT/<folder name>, so rename one of the folders (or link it under another name)"
            )
        seen[name] = data
        objects.append(BatchObject(name=name, data=data, run=Path(out) / name))
    return objects


def has_ground_truth(pipeline: Pipeline) -> bool:
    """Whether the dataset has the test views and true material maps evaluation needs."""
    try:
        check_synthetic(pipeline.scene)
    except DataError:
        return False
    return True


def run_one_object(
    data,
    run_dir,
    config: PipelineConfig,
    variants=None,
    progress: bool = True,
    log=print,
    stage: Callable[[str], None] = lambda _: None,
) -> dict | None:
    """The ordinary pipeline on one object into `run_dir`, then its evaluation and report when the
    dataset has ground truth; returns the metrics (None without ground truth). `stage` hears the
    name of each stage as it starts."""
    with Pipeline(data, run_dir, config, progress=progress, log=log) as pipeline:  # the folder is ours until evaluated
        stage("predict")
        pipeline.predict()
        stage("geometry")
        pipeline.geometry()
        for variant in variants_for_maps(variants, pipeline.has_maps):
            stage(f"refine [{variant}]")
            pipeline.refine(variant)
        if not has_ground_truth(pipeline):
            log(f"{data}: no ground truth, not evaluated")
            return None
        stage("eval")
        # the scale-aligned rows too (the TensoIR / IRGS convention), beside the unaligned ones, so benchmark tables
        # can show both protocols
        metrics = evaluate_run(
            run_dir, data, progress=progress, device=pipeline.device, backend=pipeline.backend, aligned=True
        )
        write_report(run_dir, metrics, data)
    return metrics


def finished_record(obj: BatchObject, settings_fp: str) -> dict | None:
    """The record of an object this batch finished before (same dataset, same settings), else None."""
    path = obj.run / OBJECT_RECORD
    if not path.exists():
        return None
    try:
        record = read_json(path)
    except (OSError, ValueError):
        return None
    if record.get("source") != str(obj.data) or record.get("settings") != settings_fp:
        return None
    return record


def object_result(
    obj: BatchObject,
    status: str,
    error: str | None = None,
    seconds: float | None = None,
    span: tuple[float, float] | None = None,
) -> dict:
    """The row a batch reports for one object; metrics and timings are read from its run folder.
    `span`: the wall-clock (unix) times its work started and ended here."""
    metrics_path = obj.run / "eval" / "metrics.json"
    timings_path = obj.run / "timings.json"
    ok = status != "failed"
    return {
        "name": obj.name,
        "data": str(obj.data),
        "run": str(obj.run),
        "status": status,
        "error": error,
        "seconds": seconds,
        "span": span,
        "timings": read_json(timings_path) if timings_path.exists() else {},
        "metrics": read_json(metrics_path) if ok and metrics_path.exists() else None,
    }


def one_line(exc: BaseException) -> str:
    """An exception as one line a user can act on: the library's own messages as they are, the rest
    with their type; out-of-memory says what to change."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, MatsprayError):
        return text
    if isinstance(exc, MemoryError) or "out of memory" in text.lower():
        return (
            f"out of memory ({type(exc).__name__}: {text[:200]}); "
            "use fewer workers, more CPUs/GPUs per object or a smaller preset"
        )
    return f"{type(exc).__name__}: {text[:300]}"


def process_object(
    obj: BatchObject, config: PipelineConfig, variants, settings_fp: str, threads: int, stage: Callable[[str], None]
) -> dict:
    """One object of a batch, run with `threads` torch threads; any failure is caught and returned as
    the object's one-line error. Never raises (but for Ctrl-C)."""
    start, started = time.perf_counter(), time.time()
    previous = os.environ.get("MATSPRAY_THREADS")
    os.environ["MATSPRAY_THREADS"] = str(threads)
    try:
        obj.run.mkdir(parents=True, exist_ok=True)
        with open(obj.run / OBJECT_LOG, "a", encoding="utf-8") as log_file:

            def log(message: str) -> None:
                log_file.write(f"{message}\n")
                log_file.flush()
                head = str(message).split(":", 1)[0]
                if head.startswith(("lift", "visibility")):
                    stage(head)

            metrics = run_one_object(obj.data, obj.run, config, variants, progress=False, log=log, stage=stage)
        seconds = time.perf_counter() - start
        write_json(
            obj.run / OBJECT_RECORD,
            {
                "source": str(obj.data),
                "settings": settings_fp,
                "seconds": round(seconds, 3),
                "evaluated": metrics is not None,
            },
        )
        return object_result(obj, "finished", seconds=seconds, span=(started, time.time()))
    except Exception as exc:  # noqa: BLE001 - one object's failure must not stop the others
        return object_result(
            obj, "failed", one_line(exc), seconds=time.perf_counter() - start, span=(started, time.time())
        )
    finally:
        if previous is None:
            os.environ.pop("MATSPRAY_THREADS", None)
        else:
            os.environ["MATSPRAY_THREADS"] = previous
