"""The object region of a run of a capture without masks, and how many of its Gaussians it holds.

    python -m benchmarks.region_share RUN [RUN ...]

Prints, per run: the region the photos were cut around (RUN/crop/crop.json: found on the sparse points before any
training), the one the geometry focused on (RUN/geometry/region.json) and the masks stage's (RUN/masks/region.json:
grown over the trained Gaussians), and the Gaussians of the geometry inside the last one: the object's share.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matspray.geometry.ply import vertex_count
from matspray.method.crop import read_crop_region
from matspray.method.masks import read_object_masks, read_region


def describe(run: Path) -> list[str]:
    crop, focused = read_crop_region(run / "crop"), read_region(run / "geometry")
    masks = read_object_masks(run / "masks")
    total = vertex_count(run / "geometry" / "gaussians.ply") or len(masks.inside)
    held = int(masks.inside.sum())
    return [
        f"{run}:",
        f"  crop (sparse points): {crop.describe() if crop else 'none (photos used whole)'}",
        f"  geometry's focus: {focused.describe() if focused else 'none'}",
        f"  masks: {masks.region.describe()}",
        f"  Gaussians on the object: {held} of {total} ({held / total:.1%})",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path)
    for run in parser.parse_args().runs:
        print("\n".join(describe(run)))


if __name__ == "__main__":
    main()
