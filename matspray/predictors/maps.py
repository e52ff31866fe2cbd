"""Per-view material maps, and the `materials2d/` folder every later stage reads.

On disk (DESIGN.md): `{view}_basecolor.png` sRGB-encoded, `{view}_roughness.png` and
`{view}_metallic.png` linear, all 16-bit PNG in [0, 1]; `{view}_confidence.png` (linear) where the
source gives one; `predictor.json` says what produced them. In memory: base color linear.
The folder is written as a whole: into a temporary sibling first, then renamed, so an interrupted or
failed run never leaves a partial `materials2d/`.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb, resize, srgb_to_linear, write_raw
from matspray.data.scene import View
from matspray.errors import DataError, file_error
from matspray.predictors.mapfile import read_color_map, read_scalar_map
from matspray.rundir import stage_hint

MATERIALS2D = "materials2d"
INFO_FILE = "predictor.json"
CHANNELS = ("basecolor", "roughness", "metallic")


@dataclass
class MaterialMaps:
    basecolor: Tensor  # [H, W, 3] linear RGB in [0, 1], float32
    roughness: Tensor  # [H, W] in [0, 1]
    metallic: Tensor  # [H, W] in [0, 1]
    confidence: Tensor | None = None  # [H, W] in [0, 1] (1 = certain), where the source has one

    @property
    def height(self) -> int:
        return int(self.basecolor.shape[0])

    @property
    def width(self) -> int:
        return int(self.basecolor.shape[1])

    def scalars(self) -> dict[str, Tensor]:  # name -> [H, W]
        out = {"roughness": self.roughness, "metallic": self.metallic}
        if self.confidence is not None:
            out["confidence"] = self.confidence
        return out

    def validate(self, where: str) -> "MaterialMaps":
        """Raise DataError (naming `where`) unless shapes agree, values are finite and in [0, 1]."""
        h, w = self.basecolor.shape[:2]
        if self.basecolor.ndim != 3 or self.basecolor.shape[-1] != 3:
            raise DataError(f"{where}: base color must be [H, W, 3], got {tuple(self.basecolor.shape)}")
        for name, value in {"base color": self.basecolor, **self.scalars()}.items():
            if tuple(value.shape[:2]) != (h, w) or (name != "base color" and value.ndim != 2):
                raise DataError(f"{where}: {name} is {tuple(value.shape)} but base color is {h}x{w}")
            if not torch.isfinite(value).all():
                raise DataError(f"{where}: {name} holds NaN or Inf values")
            low, high = float(value.min()), float(value.max())
            if low < 0.0 or high > 1.0:
                raise DataError(f"{where}: {name} values outside [0, 1] (min {low:.4g}, max {high:.4g})")
        return self

    def resized(self, height: int, width: int) -> "MaterialMaps":
        """The maps resampled (antialiased bilinear) to [height, width]."""

        def fit(x):
            return None if x is None else resize(x, height, width).clamp(0.0, 1.0)

        return MaterialMaps(fit(self.basecolor), fit(self.roughness), fit(self.metallic), fit(self.confidence))

    def to(self, device) -> "MaterialMaps":
        conf = None if self.confidence is None else self.confidence.to(device)
        return MaterialMaps(self.basecolor.to(device), self.roughness.to(device), self.metallic.to(device), conf)


def map_path(folder: Path, view_name: str, channel: str) -> Path:
    return Path(folder) / f"{view_name}_{channel}.png"


# ------------------------------------------------------------------------------------------ writing
def write_materials2d(run_dir, maps: dict[str, MaterialMaps], info: dict) -> Path:
    """Write `RUN/materials2d/` (16-bit PNGs + predictor.json) atomically as a folder; returns its path.

    An existing folder is replaced only once the new one is complete.
    """
    run_dir = Path(run_dir)
    final = run_dir / MATERIALS2D
    tmp = run_dir / f".{MATERIALS2D}.tmp-{os.getpid()}"
    old = run_dir / f".{MATERIALS2D}.old-{os.getpid()}"
    run_dir.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir()
        for name, m in maps.items():
            m.validate(f"maps of view '{name}'")
            write_raw(map_path(tmp, name, "basecolor"), linear_to_srgb(m.basecolor), bits=16)
            for channel, values in m.scalars().items():
                write_raw(map_path(tmp, name, channel), values, bits=16)
        record = dict(info, views=list(maps))
        (tmp / INFO_FILE).write_text(json.dumps(record, indent=2) + "\n")
        if final.exists():
            os.replace(final, old)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old.exists() and not final.exists():
            os.replace(old, final)  # put the previous folder back
        raise
    shutil.rmtree(old, ignore_errors=True)
    return final


# ------------------------------------------------------------------------------------------ reading
def read_predictor_info(run_dir) -> dict:
    path = Path(run_dir) / MATERIALS2D / INFO_FILE
    if not path.exists():
        raise file_error(path, "does not exist", "run `matspray predict` first")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, OSError, UnicodeDecodeError) as exc:
        raise file_error(
            path, f"cannot read: {' '.join(str(exc).split())}", "rerun `matspray predict` to write it again"
        ) from None
    if not isinstance(info, dict):
        raise file_error(
            path,
            f"holds a {type(info).__name__}, not the record `matspray predict` writes",
            "rerun `matspray predict` to write it again",
        )
    return info


def read_materials2d(run_dir, views: list[View]) -> dict[str, MaterialMaps]:
    """The maps of `views` (name -> MaterialMaps, base color linear) from `RUN/materials2d/`.

    Errors list every view without maps, and name any file whose size differs from its view's.
    """
    folder = Path(run_dir) / MATERIALS2D
    if not folder.is_dir():
        raise file_error(folder, "does not exist", "run `matspray predict --out RUN ...` first")
    missing = [v.name for v in views if not all(map_path(folder, v.name, c).exists() for c in CHANNELS)]
    if missing:
        shown = ", ".join(missing[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        raise file_error(
            folder,
            f"no maps for {len(missing)} of {len(views)} views: {shown}",
            "rerun `matspray predict` with the split these views come from (train, test or all)",
        )
    out = {}
    hint = stage_hint(
        map_path(folder, "any", "basecolor")
    )  # a damaged map of a finished predict stage: make the stage again
    for view in views:
        try:
            stored = read_color_map(map_path(folder, view.name, "basecolor"))
            scalars = {}
            for channel in ("roughness", "metallic", "confidence"):
                path = map_path(folder, view.name, channel)
                if channel == "confidence" and not path.exists():
                    continue
                scalars[channel] = read_scalar_map(path, channel)
        except DataError as exc:
            raise (DataError(f"{exc}; {hint}") if hint else exc) from None
        for channel, values in {"basecolor": stored, **scalars}.items():
            if tuple(values.shape[:2]) != (view.height, view.width):
                raise file_error(
                    map_path(folder, view.name, channel),
                    f"is {values.shape[1]}x{values.shape[0]} but view '{view.name}' is {view.width}x{view.height}",
                    "rerun `matspray predict` with the same dataset and downscale as this stage",
                )
        out[view.name] = MaterialMaps(
            srgb_to_linear(stored), scalars["roughness"], scalars["metallic"], scalars.get("confidence")
        )
    return out
