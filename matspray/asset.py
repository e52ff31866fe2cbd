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
VISIBILITY_FILE = "visibility.pt"  # optional: directional visibility [N, D] as uint8 (1/255 steps)


def write_visibility(path: Path, visibility: torch.Tensor) -> None:
    from matspray.data.images import save_torch_atomic

    save_torch_atomic({"format": "matspray-visibility-1", "values": (visibility.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8)}, path)


def read_visibility(path: Path, count: int) -> torch.Tensor:  # -> [count, D] float in [0, 1]
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
        values = data["values"]
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise file_error(path, f"is not a MatSpray visibility file ({exc.__class__.__name__})", "delete it to relight without shadowing") from None
    if values.dim() != 2 or values.shape[0] != count or values.dtype != torch.uint8:
        raise file_error(path, f"holds visibility {tuple(values.shape)} ({values.dtype}) but the asset has {count} Gaussians",
                         "delete it to relight without shadowing")
    return values.float() / 255.0


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
    visibility_path = folder / VISIBILITY_FILE
    if getattr(result, "visibility", None) is not None:
        write_visibility(visibility_path, result.visibility)
    elif visibility_path.exists():
        visibility_path.unlink()  # a stale file from an earlier run must not shadow this asset
    # the PLY last: its presence marks the asset complete
    extra = {name: result.materials[:, i] for i, name in enumerate(MATERIAL_PROPERTIES)}
    write_ply(folder / "asset.ply", gaussians, result.normals, extra=extra)


def read_asset(folder, device="cpu") -> Asset:
    path = Path(folder) / "asset.ply"
    gaussians, normals, extra = read_ply(path, extra=MATERIAL_PROPERTIES)
    if normals is None:
        raise file_error(path, "has no normals (nx, ny, nz)", "is this a MatSpray asset? geometry PLYs are not relightable")
    materials = torch.stack([extra[name] for name in MATERIAL_PROPERTIES], dim=-1)
    visibility_path = Path(folder) / VISIBILITY_FILE
    visibility = read_visibility(visibility_path, len(gaussians)).to(device) if visibility_path.exists() else None
    return Asset(gaussians.to(device), materials.to(device), torch.nn.functional.normalize(normals, dim=-1).to(device), visibility)


def read_history(folder) -> list[dict]:
    path = Path(folder) / "history.json"
    return read_json(path) if path.exists() else []
