"""Wall time of `matspray batch` on several `matspray synth` objects with 1, 2, ... workers.

    python -m benchmarks.batch [--preset test|demo] [--objects 4] [--workers 1 2] [--out runs/bench-batch]
                               [--in-process]

The objects (shapes in turn, seeds 0..N-1, the preset's size) are made once in OUT/data/ and reused;
every worker count runs the whole method (full variant, simulated predictor, evaluation) from
scratch into its own OUT/workers-N/. Prints each wall time, the speed-up over the first, and the
machine's CPUs and load average (the speed-up cannot exceed the CPUs free for it). With
--in-process it also times the objects one after another without Ray (Ray's own overhead).
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

from matspray.batch import BatchConfig, run_batch
from matspray.batch.demo import SHAPES, make_demo_object
from matspray.batch.runner import local_cpus
from matspray.method.config import build_config


def timed_batch(datas, out: Path, workers: int, use_ray: bool, preset: str) -> tuple[float, dict]:
    shutil.rmtree(out, ignore_errors=True)
    config = BatchConfig(pipeline=build_config(preset, predictor="simulated"), workers=workers, use_ray=use_ray)
    start = time.perf_counter()
    summary = run_batch(datas, out, config, log=lambda _: None)
    return time.perf_counter() - start, summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="test", choices=("test", "demo"))
    parser.add_argument("--objects", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/bench-batch"))
    parser.add_argument("--in-process", action="store_true", help="also time the objects one after another without Ray")
    args = parser.parse_args()
    datas = [
        make_demo_object(
            args.out / "data" / f"{i:02d}-{SHAPES[i % len(SHAPES)]}",
            args.preset,
            SHAPES[i % len(SHAPES)],
            i,
            progress=False,
        )
        for i in range(args.objects)
    ]
    print(
        f"{args.objects} {args.preset}-preset objects, full variant; {local_cpus()} CPUs; "
        f"MATSPRAY_THREADS={os.environ.get('MATSPRAY_THREADS', 'unset')}"
    )
    runs = [("in-process, one after another", 1, False)] if args.in_process else []
    runs += [(f"Ray, {w} worker{'s' if w > 1 else ''}", w, True) for w in args.workers]
    first = None
    for label, workers, use_ray in runs:
        load = os.getloadavg()[0]
        seconds, summary = timed_batch(
            datas, args.out / (f"workers-{workers}" if use_ray else "in-process"), workers, use_ray, args.preset
        )
        first = first or seconds
        per_object = [r["seconds"] for r in summary["objects"] if r["seconds"] is not None]
        print(
            f"{label:32s} wall {seconds:7.1f} s  speed-up {first / seconds:4.2f}x  "
            f"object seconds {min(per_object):.1f}..{max(per_object):.1f}  failed {len(summary['failed'])}  "
            f"load average before {load:.1f}"
        )


if __name__ == "__main__":
    main()
