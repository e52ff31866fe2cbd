"""Memory of loading a dataset at the working size: what `matspray run` holds before any stage starts.

    python -m benchmarks.load_memory [DATA] [--max-size 256]

Prints the peak resident memory of this process after `load_scene(DATA, downscale=None, max_size=...)`, the memory
still resident, and the bytes of the tensors alive (the scene itself). DATA defaults to ../shared/data/captures/stitch.
Run it more than once: glibc keeps freed memory, so the peak varies between runs of the same code.
"""

from __future__ import annotations

import argparse
import gc
import resource
from pathlib import Path

import torch

from matspray.data import load_scene

STITCH = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "captures" / "stitch"


def resident_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", nargs="?", type=Path, default=STITCH)
    parser.add_argument("--max-size", type=int, default=256, help="the working size (the demo preset's: 256)")
    args = parser.parse_args()
    scene = load_scene(args.data, downscale=None, max_size=args.max_size)
    gc.collect()
    alive = sum(o.untyped_storage().nbytes() for o in gc.get_objects() if isinstance(o, torch.Tensor))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"{args.data}: {len(scene.views)} views at {scene.train[0].width}x{scene.train[0].height} "
        f"(downscale {scene.downscale:.3g}); peak {peak:.0f} MiB, resident {resident_mib():.0f} MiB, "
        f"tensors alive {alive / 2**20:.0f} MiB"
    )


if __name__ == "__main__":
    main()
