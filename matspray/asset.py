"""The relightable asset on disk: `asset.ply` (3DGS layout + normals + base_color_{r,g,b}, roughness,
metallic), `envmap.exr` (the estimated light, when the variant learns one), `merger.pt` (the Neural
Merger, when the variant has one) and `history.json` (the loss curves)."""

from __future__ import annotations

from pathlib import Path

import torch

from matspray.errors import file_error
from matspray.geometry.ply import read_ply, write_ply
from matspray.merger import save_merger
from matspray.relight import Asset
from matspray.rundir import read_json, write_json

MATERIAL_PROPERTIES = ("base_color_r", "base_color_g", "base_color_b", "roughness", "metallic")


def write_asset(folder, gaussians, result) -> None:
    """Write a RefineResult's asset into `folder` (every file atomically)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if result.envmap is not None:
        result.envmap.save(folder / "envmap.exr")
    merger = getattr(result.source, "merger", None)
    if merger is not None:
        save_merger(merger, folder / "merger.pt")
    write_json(folder / "history.json", result.history)
    # the PLY last: its presence marks the asset complete
    extra = {name: result.materials[:, i] for i, name in enumerate(MATERIAL_PROPERTIES)}
    write_ply(folder / "asset.ply", gaussians, result.normals, extra=extra)


def read_asset(folder, device="cpu") -> Asset:
    path = Path(folder) / "asset.ply"
    gaussians, normals, extra = read_ply(path, extra=MATERIAL_PROPERTIES)
    if normals is None:
        raise file_error(path, "has no normals (nx, ny, nz)", "is this a MatSpray asset? geometry PLYs are not relightable")
    materials = torch.stack([extra[name] for name in MATERIAL_PROPERTIES], dim=-1)
    return Asset(gaussians.to(device), materials.to(device), torch.nn.functional.normalize(normals, dim=-1).to(device))


def read_history(folder) -> list[dict]:
    path = Path(folder) / "history.json"
    return read_json(path) if path.exists() else []
