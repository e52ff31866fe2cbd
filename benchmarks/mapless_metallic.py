"""How metallic a run without 2D maps makes its objects, by `refine.metallic_prior_weight`.

    python -m benchmarks.generalise --set dev --objects 3 --preset test --models ground-truth --variants no-prior \
        --refine metallic_prior_weight=W --tag mpW --out DIR          # once per weight W
    python -m benchmarks.mapless_metallic DIR

Reads every run the generalise passes left in DIR (DIR/objects/OBJECT/runs/RUN with an asset-no-prior) and prints,
per object and weight, the no-prior asset's mean metallic and the share of its Gaussians above 0.5, beside the mean
of the object's true metallic over its test views' masks. The relighting and metallic PSNR of the same runs are in
DIR/results-mpW.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matspray.data.images import read_image, read_raw
from matspray.method.asset import read_asset
from matspray.rundir import RunDir


def true_metallic(data: Path) -> float | None:
    """The mean true metallic over the test views' masks (their `*_metallic.png` maps beside the renders, linear)."""
    total = count = 0.0
    for path in sorted((data / "test").glob("*_metallic.png")):
        values = read_raw(path)[..., 0]
        _, alpha = read_image(path.with_name(path.name.replace("_metallic", "")))
        inside = alpha > 0.5 if alpha is not None else values >= 0
        total, count = total + float(values[inside].sum()), count + float(inside.sum())
    return total / count if count else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="the --out folder of the generalise passes")
    args = parser.parse_args(argv)
    print("| object | true metallic | weight | mean metallic | Gaussians > 0.5 |\n|---|---|---|---|---|")
    for obj in sorted((args.out / "objects").iterdir()):
        truth = true_metallic(obj / "data")
        rows = []
        for run in sorted((obj / "runs").iterdir()):
            if (run / "asset-no-prior" / "asset.ply").is_file():
                weight = RunDir(run).config().get("refine", {}).get("metallic_prior_weight", 0.0)
                metallic = read_asset(run / "asset-no-prior").materials[:, 4]
                rows.append((weight, float(metallic.mean()), float((metallic > 0.5).float().mean())))
        for weight, mean, above in sorted(rows):
            shown = "—" if truth is None else f"{truth:.3f}"
            print(f"| {obj.name} | {shown} | {weight:g} | {mean:.3f} | {100 * above:.0f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
