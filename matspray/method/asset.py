"""The relightable asset on disk: `asset.ply` (3DGS layout + normals + base_color_{r,g,b}, roughness,
metallic), `envmap.exr` (the estimated light, when the variant learns one), `merger.pt` (the Neural
Merger, when the variant has one), `camera_light.json` (the flash estimated beside the light, when the photos had one:
`refine.camera_light`) and `history.json` (the loss curves)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from matspray.data.images import save_torch_atomic, write_image
from matspray.errors import file_error
from matspray.gaussians import Gaussians
from matspray.geometry.ply import read_ply, write_ply
from matspray.material import CHANNELS, N_CHANNELS
from matspray.method.merger import save_merger
from matspray.method.refine.camera_light import CAMERA_LIGHT_FILE, CameraLight
from matspray.rundir import read_record, stage_hint, write_json

VISIBILITY_FILE = "visibility.pt"  # optional: directional visibility [N, D] as uint8 (1/255 steps)
ENVMAP_FILE = "envmap.exr"  # the estimated light: linear HDR lat-long [H, 2H, 3], `render.latlong` orientation
LOSS_TERMS = ("material", "photo")  # what the report draws of a history entry
ENVMAP_PREVIEW = "envmap.png"  # the same, tone-mapped for people (exposure: its 99th percentile at 0.9, sRGB)


@dataclass
class Asset:
    """What refinement produces: Gaussians with PBR materials and shading normals."""

    gaussians: Gaussians
    materials: Tensor  # [N, 5] `matspray.material` layout: base color rgb (linear), roughness, metallic
    normals: Tensor  # [N, 3] unit; sign is fixed per view when rendering
    visibility: Tensor | None = None  # [N, D] directional visibility (`render.visibility`); None = no shadowing
    camera_light: CameraLight | None = None  # the capture's flash (scoring its photos); relighting leaves it out

    def __post_init__(self):
        n = len(self.gaussians)
        if self.materials.shape != (n, N_CHANNELS) or self.normals.shape != (n, 3):
            raise ValueError(
                f"asset: materials must be [{n}, {N_CHANNELS}] and normals [{n}, 3], "
                f"got {tuple(self.materials.shape)}, {tuple(self.normals.shape)}"
            )
        if self.visibility is not None and self.visibility.shape[0] != n:
            raise ValueError(f"asset: visibility must be [{n}, D], got {tuple(self.visibility.shape)}")


def envmap_preview(map: Tensor) -> Tensor:  # [H, 2H, 3] linear radiance -> [H, 2H, 3] linear, scaled for an 8-bit PNG
    """The light scaled so its 99th percentile reaches 0.9 (sRGB-encoded on writing), so that a person
    sees its structure; the EXR keeps the real values."""
    peak = torch.quantile(map.detach().float().flatten(), 0.99).clamp_min(1e-8)
    return (map.detach() * (0.9 / peak)).clamp(0.0, 1.0)


def write_visibility(path: Path, visibility: torch.Tensor) -> None:
    save_torch_atomic(
        {
            "format": "matspray-visibility-1",
            "values": (visibility.detach().cpu().clamp(0, 1) * 255).round().to(torch.uint8),
        },
        path,
    )


def read_visibility(path: Path, count: int) -> torch.Tensor:  # -> [count, D] float in [0, 1]
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
        values = data["values"]
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise file_error(
            path,
            f"is not a MatSpray visibility file ({exc.__class__.__name__})",
            "delete it to relight without shadowing",
        ) from None
    if not isinstance(values, torch.Tensor):
        raise file_error(
            path,
            f"holds a {type(values).__name__} as its values, not a tensor",
            "delete it to relight without shadowing",
        )
    if values.dim() != 2 or values.shape[0] != count or values.dtype != torch.uint8:
        raise file_error(
            path,
            f"holds visibility {tuple(values.shape)} ({values.dtype}) but the asset has {count} Gaussians",
            "delete it to relight without shadowing",
        )
    return values.float() / 255.0


def write_asset(folder, gaussians, result) -> None:
    """Write a RefineResult's asset into `folder` (every file atomically)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if result.envmap is not None:
        result.envmap.save(folder / ENVMAP_FILE)
        write_image(folder / ENVMAP_PREVIEW, envmap_preview(result.envmap.map))
    merger = getattr(result.source, "merger", None)
    if merger is not None:
        save_merger(merger, folder / "merger.pt")
    write_json(folder / "history.json", result.history)
    visibility_path = folder / VISIBILITY_FILE
    if getattr(result, "visibility", None) is not None:
        write_visibility(visibility_path, result.visibility)
    elif visibility_path.exists():
        visibility_path.unlink()  # a stale file from an earlier run must not shadow this asset
    flash_path = folder / CAMERA_LIGHT_FILE
    if getattr(result, "camera_light", None) is not None:
        result.camera_light.save(flash_path)
    elif flash_path.exists():
        flash_path.unlink()  # nor light it with an earlier run's flash
    # the PLY last: its presence marks the asset complete
    extra = {name: result.materials[:, i] for i, name in enumerate(CHANNELS)}
    write_ply(folder / "asset.ply", gaussians, result.normals, extra=extra)


def read_asset(folder, device="cpu") -> Asset:
    path = Path(folder) / "asset.ply"
    gaussians, normals, extra = read_ply(path, extra=CHANNELS)
    if normals is None:
        raise file_error(
            path,
            "has no normals (nx, ny, nz)",
            stage_hint(path) or "is this a MatSpray asset? geometry PLYs are not relightable",
        )
    materials = torch.stack([extra[name] for name in CHANNELS], dim=-1)
    visibility_path = Path(folder) / VISIBILITY_FILE
    visibility = read_visibility(visibility_path, len(gaussians)).to(device) if visibility_path.exists() else None
    flash_path = Path(folder) / CAMERA_LIGHT_FILE
    camera_light = CameraLight.load(flash_path).to(device) if flash_path.exists() else None
    return Asset(
        gaussians.to(device),
        materials.to(device),
        torch.nn.functional.normalize(normals, dim=-1).to(device),
        visibility,
        camera_light,
    )


def read_history(folder) -> list[dict]:
    """The loss curves of a refinement (history.json): one {"step": n, term: loss, ...} per logged step;
    [] without one."""
    path = Path(folder) / "history.json"
    if not path.exists():
        return []
    hint = "delete it: it only holds the loss curves the report draws"
    history = read_record(path, hint)
    finite = lambda v: not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)  # noqa: E731
    if not isinstance(history, list) or not all(
        isinstance(r, dict) and finite(r.get("step")) and all(finite(v) for k, v in r.items() if k in LOSS_TERMS)
        for r in history
    ):
        raise file_error(path, "is not a list of logged steps with finite losses", hint)
    return history
