"""Peak resident memory of one `matspray run`, sampled from outside (for code whose stage records keep no peak).

    MATSPRAY_THREADS=1 nice -n 5 python -m benchmarks.run_memory --out PREFIX -- \\
        --data ../shared/data/captures/stitch --out RUN [--set ...]

Runs `python -m matspray run ARGS` as a child, samples its resident memory (and its children's) every 0.25 s into
PREFIX.rss ("seconds MiB" a line), writes its output with the second each line came into PREFIX.log, and prints the
peak, the peak before the first line that names each stage ("points:", "geometry:", ...), and the peak each stage's
record keeps (`peak_memory_mib`, code that records it)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil


def sample(process: psutil.Process, path: Path, start: float, done: threading.Event) -> None:
    with path.open("w") as out:
        while not done.is_set():
            try:
                rss = process.memory_info().rss + sum(c.memory_info().rss for c in process.children(recursive=True))
            except psutil.Error:
                rss = 0
            out.write(f"{time.time() - start:.2f} {rss / 2**20:.0f}\n")
            out.flush()
            done.wait(0.25)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="prefix of the .rss and .log files")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="-- then the arguments of `matspray run`")
    args = parser.parse_args(argv)
    run_args = [a for a in args.args if a != "--"]
    start, done = time.time(), threading.Event()
    child = subprocess.Popen(
        [sys.executable, "-m", "matspray", "run", *run_args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        bufsize=1,
    )
    sampler = threading.Thread(target=sample, args=(psutil.Process(child.pid), Path(f"{args.out}.rss"), start, done))
    sampler.start()
    with open(f"{args.out}.log", "w") as log:
        for line in child.stdout:
            log.write(f"{time.time() - start:8.1f} {line}")
            log.flush()
    child.wait()
    done.set()
    sampler.join()
    rss = [tuple(map(float, line.split())) for line in Path(f"{args.out}.rss").read_text().splitlines()]
    print(f"exit {child.returncode}; peak {max(m for _, m in rss) / 1024:.2f} GB over {rss[-1][0]:.0f} s")
    firsts = {}
    for line in Path(f"{args.out}.log").read_text().splitlines():
        second, _, text = line.strip().partition(" ")
        stage = text.split(":")[0].split(" ")[0]
        if stage in ("points", "geometry", "masks", "lift", "refine") and stage not in firsts:
            firsts[stage] = float(second)
    for stage, second in firsts.items():
        before = [m for s, m in rss if s <= second]
        print(f"  peak before the first '{stage}' line ({second:.0f} s): {max(before or [0]) / 1024:.2f} GB")
    run = Path(run_args[run_args.index("--out") + 1]) if "--out" in run_args else None
    for record in sorted(run.glob("*/stage.json")) if run else []:
        peak = json.loads(record.read_text()).get("peak_memory_mib")
        if peak is not None:
            print(f"  {record.parent.name}: {peak / 1024:.2f} GB (its record)")
    return child.returncode


if __name__ == "__main__":
    raise SystemExit(main())
