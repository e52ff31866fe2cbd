"""Round trip of a procedural object through glTF: `synth` writes object.glb, `synth --asset object.glb
--placement keep` with the same settings renders it again; PSNR of every render and ground-truth map.

    python -m benchmarks.gltf_roundtrip [--shape composite] [--res 128] [--views 10] [--test-views 4] [--spp 64]

Both renders use the same sampler seeds, so what differs is the 8-bit quantisation of object.glb's
textures (and float32 vertex positions); PSNR over whole images, values in [0, 1].
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from matspray.data.images import read_raw
from matspray.synth import SynthConfig, make_object

KINDS = {
    "render": "r_???.png",
    "basecolor": "r_???_basecolor.png",
    "roughness": "r_???_roughness.png",
    "metallic": "r_???_metallic.png",
    "relit": "r_???_relight_*.png",
}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--test-views", type=int, default=4)
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args()
    settings = dict(
        seed=args.seed, resolution=args.res, train_views=args.views, test_views=args.test_views, spp=args.spp
    )
    with tempfile.TemporaryDirectory() as folder:
        made, again = Path(folder) / "made", Path(folder) / "again"
        start = time.perf_counter()
        make_object(SynthConfig(shape=args.shape, **settings), made, progress=False, notify=lambda _: None)
        middle = time.perf_counter()
        make_object(
            SynthConfig(asset=str(made / "object.glb"), placement="keep", **settings),
            again,
            progress=False,
            notify=lambda _: None,
        )
        end = time.perf_counter()
        print(
            f"{args.shape} seed {args.seed}, {args.res} px, {args.views} train + {args.test_views} test "
            f"views, {args.spp} spp; "
            f"object.glb {(made / 'object.glb').stat().st_size / 1e6:.1f} MB; synth {middle - start:.1f} s, "
            f"synth --asset {end - middle:.1f} s"
        )
        for kind, pattern in KINDS.items():
            values = [
                psnr(read_raw(f).numpy(), read_raw(again / f.relative_to(made)).numpy())
                for split in ("train", "test")
                for f in sorted((made / split).glob(pattern))
            ]
            print(f"{kind:>10}: {len(values):3d} images, PSNR min {min(values):.2f} dB, mean {np.mean(values):.2f} dB")


if __name__ == "__main__":
    main()
