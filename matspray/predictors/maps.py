"""Per-view material maps, and the `materials2d/` folder every later stage reads.

On disk (docs/data.md): `{view}_basecolor.png` sRGB-encoded, `{view}_roughness.png` and
`{view}_metallic.png` linear, all 16-bit PNG in [0, 1]; `{view}_confidence.png` (linear) where the
source gives one; `{view}_normal.exr` (float, the raw vectors) where the source gives normals, in the
space `predictor.json` names as `normal_space` (conventions: `matspray.predictors.normalmaps`);
`predictor.json` says what produced them. In memory: base color linear.
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

from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb, read_raw, resize, srgb_to_linear, write_raw
from matspray.data.scene import View
from matspray.errors import DataError, MatsprayError, file_error
from matspray.material import stack
from matspray.predictors import CHANNELS
from matspray.predictors.mapfile import read_color_map, read_scalar_map
from matspray.predictors.normalmaps import NORMAL_SPACES, camera_to_world, normal_problem, renormalised
from matspray.rundir import read_mapping, stage_hint

MATERIALS2D = "materials2d"
INFO_FILE = "predictor.json"


@dataclass
class MaterialMaps:
    basecolor: Tensor  # [H, W, 3] linear RGB in [0, 1], float32
    roughness: Tensor  # [H, W] in [0, 1]
    metallic: Tensor  # [H, W] in [0, 1]
    confidence: Tensor | None = None  # [H, W] in [0, 1] (1 = certain), where the source has one
    normals: Tensor | None = None  # [H, W, 3] unit vectors, (0, 0, 0) where there is none; None: no normal map
    normal_space: str = "camera"  # of `normals`: "camera" (the view's OpenCV camera axes) or "world"

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
        if self.normal_space not in NORMAL_SPACES:
            raise DataError(f"{where}: normal space '{self.normal_space}' is not one of {', '.join(NORMAL_SPACES)}")
        if self.normals is not None:
            problem = normal_problem(self.normals)
            if problem:
                raise DataError(f"{where}: normals {problem}")
            if tuple(self.normals.shape[:2]) != (h, w):
                raise DataError(f"{where}: normals are {tuple(self.normals.shape)} but base color is {h}x{w}")
        return self

    def resized(self, height: int, width: int) -> "MaterialMaps":
        """The maps resampled (antialiased bilinear) to [height, width]."""

        def fit(x):
            return None if x is None else resize(x, height, width).clamp(0.0, 1.0)

        # averaging vectors shortens them (most at the object's edge): back to unit length after resampling
        normals = None if self.normals is None else renormalised(resize(self.normals, height, width))
        return MaterialMaps(
            fit(self.basecolor),
            fit(self.roughness),
            fit(self.metallic),
            fit(self.confidence),
            normals,
            self.normal_space,
        )

    def to(self, device) -> "MaterialMaps":
        def move(x):
            return None if x is None else x.to(device)

        return MaterialMaps(
            self.basecolor.to(device),
            self.roughness.to(device),
            self.metallic.to(device),
            move(self.confidence),
            move(self.normals),
            self.normal_space,
        )


def world_normals(
    maps: MaterialMaps | Tensor,  # MaterialMaps with normals, or a normal map [H, W, 3] in `space`
    camera: Camera,  # the camera of the view the map belongs to
    space: str = "camera",  # the space of a bare tensor (MaterialMaps say their own)
) -> Tensor:  # [H, W, 3] world-space unit normals, (0, 0, 0) where there is none
    """A view's normal map in world space, whichever space it was predicted in."""
    if isinstance(maps, MaterialMaps):
        if maps.normals is None:
            raise DataError("these maps have no normal map")
        normals, space = maps.normals, maps.normal_space
    else:
        normals = maps
    if space not in NORMAL_SPACES:
        raise DataError(f"normal space '{space}' is not one of {', '.join(NORMAL_SPACES)}")
    return normals if space == "world" else camera_to_world(normals, camera)


def maps_to_tensor(maps: MaterialMaps) -> Tensor:  # -> [H, W, 5]
    return stack(maps.basecolor, maps.roughness, maps.metallic)


def predicted_normal_maps(maps: dict, views: list) -> list[torch.Tensor] | None:
    """The views' predicted normal maps in world space [H, W, 3] (zero where a view has none), or None when the
    predictor gave no normals at all."""
    if not any(maps[v.name].normals is not None for v in views):
        return None
    return [
        world_normals(maps[v.name], v.camera)
        if maps[v.name].normals is not None
        else torch.zeros(v.height, v.width, 3, device=v.camera.viewmat.device)
        for v in views
    ]


def without_normals(folder: Path, stage: str) -> str:
    """The line that says `stage` runs without the predicted normals its weight asks for: the maps in `folder` have
    none."""
    return (
        f"{stage}: the 2D maps ({folder}) have no normal maps, so it runs without predicted normals (they come with "
        "simulated, ground-truth, files: with *_normal files, marigold --normals-weights)"
    )


def map_path(folder: Path, view_name: str, channel: str) -> Path:
    return Path(folder) / f"{view_name}_{channel}.png"


def normal_path(folder: Path, view_name: str) -> Path:  # float vectors: EXR, not a display PNG
    return Path(folder) / f"{view_name}_normal.exr"


def normal_space_of(maps: dict[str, MaterialMaps]) -> str | None:
    """The one space of the maps' normals (None when no view has normals); one folder records one space."""
    spaces = sorted({m.normal_space for m in maps.values() if m.normals is not None})
    if len(spaces) > 1:
        raise DataError(f"the views' normals are in different spaces ({', '.join(spaces)}); one run stores one")
    return spaces[0] if spaces else None


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
    space = normal_space_of(maps)
    try:
        tmp.mkdir()
        for name, m in maps.items():
            m.validate(f"maps of view '{name}'")
            write_raw(map_path(tmp, name, "basecolor"), linear_to_srgb(m.basecolor), bits=16)
            for channel, values in m.scalars().items():
                write_raw(map_path(tmp, name, channel), values, bits=16)
            if m.normals is not None:
                write_raw(normal_path(tmp, name), m.normals)
        record = dict(info, views=list(maps))
        if space is not None:
            record["normal_space"] = space
        else:
            record.pop("normal_space", None)  # no normal files: a stale space would only mislead
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
    return read_mapping(path, "rerun `matspray predict` to write it again", "the record `matspray predict` writes")


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
    space = None
    if any(normal_path(folder, v.name).exists() for v in views):
        space = recorded_normal_space(run_dir)
    for view in views:
        try:
            stored = read_color_map(map_path(folder, view.name, "basecolor"))
            scalars = {}
            for channel in ("roughness", "metallic", "confidence"):
                path = map_path(folder, view.name, channel)
                if channel == "confidence" and not path.exists():
                    continue
                scalars[channel] = read_scalar_map(path, channel)
            normals = read_normal_file(normal_path(folder, view.name)) if space is not None else None
        except DataError as exc:
            raise (DataError(f"{exc}; {hint}") if hint else exc) from None
        if normals is not None:
            scalars["normal"] = normals  # checked for size with the rest
        for channel, values in {"basecolor": stored, **scalars}.items():
            if tuple(values.shape[:2]) != (view.height, view.width):
                raise file_error(
                    normal_path(folder, view.name) if channel == "normal" else map_path(folder, view.name, channel),
                    f"is {values.shape[1]}x{values.shape[0]} but view '{view.name}' is {view.width}x{view.height}",
                    "rerun `matspray predict` with the same dataset and downscale as this stage",
                )
        out[view.name] = MaterialMaps(
            srgb_to_linear(stored),
            scalars["roughness"],
            scalars["metallic"],
            scalars.get("confidence"),
            normals,
            space or "camera",
        )
    return out


def recorded_normal_space(run_dir) -> str:
    """The `normal_space` predictor.json records for the folder's normal files (DataError when it names none)."""
    space = read_predictor_info(run_dir).get("normal_space")
    if space not in NORMAL_SPACES:
        raise file_error(
            Path(run_dir) / MATERIALS2D / INFO_FILE,
            f"names no valid normal_space (got {space!r}; expected one of {', '.join(NORMAL_SPACES)}) "
            "but the folder holds normal files",
            "rerun `matspray predict` to write the folder again",
        )
    return space


def read_normal_file(path: Path) -> Tensor | None:  # [H, W, 3] unit or zero; None when there is no file
    """A stored normal map of the internal convention (raw float vectors, EXR), checked."""
    if not path.exists():
        return None
    try:
        values = read_raw(path)
    except MatsprayError:
        raise
    except Exception as exc:  # decoders raise their own types for truncated or corrupt files
        raise file_error(path, f"cannot read image: {exc}") from None
    if values.shape[-1] == 4:  # an alpha channel carries nothing the zero vectors do not
        values = values[..., :3]
    problem = normal_problem(values)
    if problem:
        raise file_error(path, problem)
    return renormalised(values)
