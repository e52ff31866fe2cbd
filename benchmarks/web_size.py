"""The size of `matspray export --web`'s folder and of `--splats`' glb: for a run's asset, or for N random Gaussians
(a synthetic stand-in: random values deflate worse than a trained asset's, so its figure is an upper bound).

    python -m benchmarks.web_size --gaussians 200000
    python -m benchmarks.web_size --run RUN
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from matspray.gaussians import Gaussians
from matspray.method.asset import Asset


def random_asset(count: int, seed: int = 0) -> Asset:
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=g) * 2 - 1
    gaussians = Gaussians(
        means,
        torch.rand(count, 3, generator=g) * 3 - 7,  # scales e^-7 .. e^-4
        torch.randn(count, 4, generator=g),
        torch.randn(count, generator=g) * 2,
        torch.zeros(count, 1, 3),
    )
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return Asset(gaussians, torch.rand(count, 5, generator=g), normals)


def folder_size(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(folder.iterdir())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=200_000)
    parser.add_argument("--run", type=Path, help="measure this run's asset instead of random Gaussians")
    args = parser.parse_args()
    from matspray.export.splats import write_splats
    from matspray.method.relight import orbit_spec
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.web.page import write_page

    with tempfile.TemporaryDirectory() as tmp:
        if args.run is not None:
            from matspray.cli import main as cli

            cli(["export", "--run", str(args.run), "--web", f"{tmp}/web", "--splats", f"{tmp}/splats.glb"])
            what = f"{args.run}"
        else:
            asset = random_asset(args.gaussians)
            light = EnvironmentMap.constant(1.0, 16, learnable=False)
            spec = orbit_spec(list(_ring()), torch.zeros(3), (0.0, 0.0, 1.0))
            write_page(f"{tmp}/web", asset, spec, light.map)
            write_splats(f"{tmp}/splats.glb", asset, light.prefilter(), light.map, spec)
            what = f"{args.gaussians} random Gaussians"
        sizes = folder_size(Path(tmp) / "web")
        total = sum(sizes.values())
        parts = ", ".join(f"{name} {size / 1e6:.2f} MB" for name, size in sizes.items())
        print(f"{what}: web folder {total / 1e6:.2f} MB ({parts})")
        print(f"{what}: splats glb {(Path(tmp) / 'splats.glb').stat().st_size / 1e6:.2f} MB")


def _ring():
    from matspray.data import Camera

    yield Camera.look_at([4.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.75, 64, 64)
    yield Camera.look_at([0.0, 4.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.75, 64, 64)


if __name__ == "__main__":
    main()
