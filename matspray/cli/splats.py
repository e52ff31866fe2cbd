"""`matspray export --splats FILE.glb [LIGHT]` and `--web DIR`: the run-folder glue (which asset, which light, which
orbit); `matspray.export.splats` and `matspray.web` do the work."""

from __future__ import annotations

import math
from pathlib import Path

BAKE_ENV_HEIGHT = 64  # rows of the light the splats' colour is baked under (relight's default --env-height)


def asset_source(args, device):
    """(asset, estimated light [H, 2H, 3] or None, orbit spec) of `--run`: a run folder or a splats .glb."""
    from matspray.errors import ConfigError

    if args.run.suffix.lower() == ".glb":
        from matspray.export.splats import read_splats_asset

        if args.variant is not None or args.data is not None:
            raise ConfigError("--variant and --data are for run folders; a .glb holds one asset and its orbit")
        splats = read_splats_asset(args.run, device)
        if not splats.view:
            raise ConfigError(f"{args.run}: records no orbit; export it again with `matspray export --splats`")
        return splats.asset, splats.light, splats.view
    from matspray.cli.relight import orbit_reference
    from matspray.data import load_run_scene
    from matspray.method.asset import ENVMAP_FILE, read_asset
    from matspray.method.relight import orbit_spec
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.rundir import RunDir

    run = RunDir(args.run).require()
    folder = run.asset_path(args.variant or run.default_variant())
    asset = read_asset(folder, device=device)
    light = EnvironmentMap.from_file(folder / ENVMAP_FILE).map.detach() if (folder / ENVMAP_FILE).exists() else None
    reference, center, up = orbit_reference(run, load_run_scene(run, args.data))
    return asset, light, orbit_spec(reference, center, up)


def bake_light(spec: str | None, estimated, device):
    """The light the splats' colour is baked under, prefiltered: `spec` (relight's --env names and files), or the
    estimated light when None."""
    from matspray.errors import ConfigError
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.render.shade.lights import load_envmap

    if spec is None and estimated is None:
        raise ConfigError(
            "this asset has no estimated light: name one to bake the splats under, --splats FILE.glb LIGHT"
        )
    light = estimated if spec is None else load_envmap(spec)[1]
    return EnvironmentMap.from_tensor(light.to(device), height=BAKE_ENV_HEIGHT, learnable=False).prefilter()


def write_web_page(args, asset, view: dict, estimated, device) -> list[Path]:
    """The page of `asset` with the Gaussians it draws (`web.detail`), chosen under its estimated light (when it has
    one) and the packaged light that shows most what is left out."""
    import torch

    from matspray.web.detail import CHECK_LIGHT, page_gaussians, subset
    from matspray.web.page import BACKGROUND, write_page

    lights = []  # --web DIR inf keeps every Gaussian: nothing is checked, so no light is prefiltered for it
    if not math.isinf(args.web_psnr):
        lights.append(bake_light(CHECK_LIGHT, estimated, device))
        if estimated is not None:
            lights.append(bake_light(None, estimated, device))
    background = torch.tensor(BACKGROUND, device=device)
    detail = page_gaussians(asset, view, lights, background, args.web_psnr, progress=True)
    drawn = int(detail.keep.sum())
    if drawn < len(asset.gaussians):
        print(
            f"web page: draws {drawn} of the asset's {len(asset.gaussians)} Gaussians, its frames {detail.psnr:.1f} dB "
            "from the whole asset's (--web DIR inf draws every one)"
        )
    return write_page(args.web, subset(asset, detail.keep), view, estimated, drawn_of=len(asset.gaussians))


def export_splats_and_web(args, device) -> list[Path]:
    """Write what --splats and --web ask for; returns the files written."""
    from matspray.errors import ConfigError

    written = []
    if args.web is not None:
        from matspray.web.page import bundle_path

        bundle_path()  # refused before any work when the page's script is not built
    asset, estimated, view = asset_source(args, device)
    if args.splats is not None:
        from matspray.export.splats import write_splats, write_spz_file

        path = Path(args.splats[0])
        light = bake_light(args.splats[1] if len(args.splats) > 1 else None, estimated, device)
        if path.suffix.lower() == ".spz":
            try:
                written += write_spz_file(path, asset, light, estimated, view)
            except ImportError:
                raise ConfigError("writing .spz needs gsply: pip install 'matspray[export]'") from None
        else:
            written += write_splats(path, asset, light, estimated, view)
    if args.web is not None:
        written += write_web_page(args, asset, view, estimated, device)
    return written
