"""The page's folder: index.html, the page's script and the data scripts, nothing that a browser fetches from
elsewhere (`matspray export --web DIR`)."""

from __future__ import annotations

import functools
import os
import shutil
from pathlib import Path

import torch

from matspray.errors import ConfigError
from matspray.method.asset import Asset
from matspray.render.shade.lights import BUILTINS, hdri_files, load_envmap
from matspray.web.pack import asset_script, lights_script, page_light

PACKAGE = Path(__file__).parent
BUNDLE = PACKAGE / "dist" / "matspray-web.js"  # made by `make setup` (npm: three, esbuild); shipped in the package
PAGE_SIZE = 512  # pixels of the page's square view
BACKGROUND = (0.02, 0.02, 0.02)  # linear, behind the object (src/main.js BACKGROUND)


def bundle_path() -> Path:
    if not BUNDLE.is_file():
        raise ConfigError(
            f"the page's script {BUNDLE} is not built: `make setup` builds it with npm (three.js and esbuild), "
            "or run `make web` once node and npm are installed"
        )
    return BUNDLE


def packaged_lights() -> list[tuple[str, torch.Tensor]]:
    """Every light MatSpray ships: the built-ins, then the packaged HDRIs (a name a built-in has taken keeps its
    suffix, as `load_envmap` reaches it), each at the page's LIGHT_HEIGHT rows."""
    return list(_packaged_page_lights())


@functools.cache
def _packaged_page_lights() -> tuple[tuple[str, torch.Tensor], ...]:
    # made once a process: they take seconds (the built-ins are drawn at full size first) and never change
    names = list(BUILTINS) + [p.stem if p.stem not in BUILTINS else p.name for p in hdri_files().values()]
    return tuple((name, torch.from_numpy(page_light(load_envmap(name)[1]))) for name in names)


def page_view(spec: dict, size: int = PAGE_SIZE) -> dict:
    """The orbit of `method.relight.orbit_spec` for the page's square view of `size` pixels (the same horizontal
    field of view)."""
    scale = size / spec["width"]
    return {**spec, "fx": spec["fx"] * scale, "fy": spec["fy"] * scale, "width": size, "height": size}


def write_page(
    folder, asset: Asset, spec: dict, estimated: torch.Tensor | None = None, drawn_of: int | None = None
) -> list[Path]:
    """Write the page for `asset` into `folder`: its orbit `spec` (`method.relight.orbit_spec`), the `estimated`
    light [H, 2H, 3] first (when given), then the packaged ones; `drawn_of`: the Gaussians of the asset the page's
    were chosen from (`web.detail`), for its status line. Returns the files written.

    The files are made in a hidden folder inside it first and moved out only once all are made, index.html last: an
    export that fails or is stopped leaves the page that was there before, not one whose files are of two exports."""
    bundle = bundle_path()
    folder = Path(folder)
    lights = ([("estimated", estimated)] if estimated is not None else []) + packaged_lights()
    texts = {
        "asset.js": asset_script(asset, page_view(spec), {"drawnOf": drawn_of or len(asset.gaussians)}),
        "lights.js": lights_script(lights),
        "index.html": (PACKAGE / "static" / "index.html").read_text(),
    }
    copies = {"matspray-web.js": bundle, "LICENSES.txt": PACKAGE / "static" / "LICENSES.txt"}  # three.js's MIT notice
    names = [*copies, *texts]  # the order they move in: index.html, which names the others, last
    folder.mkdir(parents=True, exist_ok=True)
    stage = folder / f".page.tmp-{os.getpid()}"  # inside: the folder may be "." and its parent not ours to write
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        for name, text in texts.items():
            (stage / name).write_text(text)
        for name, source in copies.items():
            shutil.copyfile(source, stage / name)
        for name in names:
            os.replace(stage / name, folder / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return [folder / name for name in names]
