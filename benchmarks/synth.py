"""Time to make the default demo object of `matspray synth` (128 px, 40 train + 10 test views, two
relight lights, 64 spp), per shape; target under 3 minutes on 2 CPU cores.

    python -m benchmarks.synth                   (from the repository root; default: composite, the slowest)
    python -m benchmarks.synth --shape sphere --shape torus
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from matspray.synth import SynthConfig, make_object
from matspray.synth.shapes import SHAPES


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--shape", action="append", choices=sorted(SHAPES), help="shapes to time (default composite)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for shape in args.shape or ["composite"]:
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            result = make_object(
                SynthConfig(shape=shape, seed=args.seed), Path(folder) / "object", progress=False, notify=lambda _: None
            )
            seconds = time.perf_counter() - start
        print(
            f"{shape:>13}: {seconds:6.1f} s for 40 train + 10 test views at 128 px, 64 spp, relit under "
            f"{' and '.join(result.relight_envs)} ({result.variant})"
        )


if __name__ == "__main__":
    main()
