"""A working size that follows the object: a capture without masks has each photo cut to the object's box, with a
margin, before it is brought to the working size, so that the object gets the pixels and not the room.

The box comes before any training, from the capture's sparse points (its own, or the `points` stage's) inside the
object region (matspray.geometry.region: `--object-bounds`, else the automatic rule on the points), projected into each
view: the box between the `quantile` and 1 - `quantile` of their pixels, grown by `margin` of its size on each side.
Each window then takes the frame's aspect ratio and is brought to the size the whole photo would have had, so every
view keeps its size and only its intrinsics change (focal length and principal point). Nothing is enlarged: a window
is never smaller than that size in the photo's own pixels. A view whose box does not fit in its photo keeps the
whole photo, and a capture whose windows would gain little (on average more than 1 / `min_gain` of the photo's
side) is not cut at all.

The windows are fractions of the photo (resolution free), kept in the run (`RUN/crop/crop.json`, written by
matspray.method.crop): every command that reads the run's photos cuts them the same way
(`matspray.data.loader.load_run_scene`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.scene import View
from matspray.errors import DataError, SettingError, file_error
from matspray.files import read_json
from matspray.settings import setting

CROP_FILE = "crop.json"
WHOLE_FRAME = (0.0, 0.0, 1.0, 1.0)  # a window that keeps the whole photo
MIN_POINTS = 16  # a view sees fewer of the object's points than this: it keeps the whole photo


@dataclass(frozen=True)
class CropConfig:
    enabled: bool = setting(
        True,
        "a capture without masks has each photo cut to its object (from the sparse points) before the working size",
    )
    margin: float = setting(0.15, "added to the object's box on each side, as a fraction of the box's size")
    quantile: float = setting(0.01, "the box holds the object's projected points from this quantile to 1 - it")
    min_gain: float = setting(1.2, "cut only when the windows' side is on average at most 1 / this of the photo's")

    def __post_init__(self):
        if not 0.0 <= self.margin <= 2.0:
            raise SettingError("crop.margin", f"must be in [0, 2], got {self.margin}")
        if not 0.0 <= self.quantile < 0.5:
            raise SettingError("crop.quantile", f"must be in [0, 0.5), got {self.quantile}")
        if self.min_gain < 1.0:
            raise SettingError("crop.min_gain", f"must be >= 1, got {self.min_gain}")


@dataclass(frozen=True)
class CropPlan:
    """Where each photo is cut: `windows` maps a view's name to (left, top, right, bottom) as fractions of its photo;
    every window becomes a frame of `size` (width, height) pixels."""

    size: tuple[int, int]
    windows: dict[str, tuple[float, float, float, float]]

    def fit(self, view: View) -> View:
        """`view` (at its photo's size) cut to its window and brought to `size`."""
        window = self.windows.get(view.name)
        if window is None:
            raise DataError(
                f"view '{view.name}' has no crop window in the run (crop/{CROP_FILE}); "
                "delete the run's crop/ folder to cut the photos again"
            )
        left, top = round(window[0] * view.width), round(window[1] * view.height)
        right, bottom = round(window[2] * view.width), round(window[3] * view.height)
        return view.cropped(left, top, right - left, bottom - top).resized(*self.size)

    def mean_side(self) -> float:
        """The windows' mean side as a fraction of the photo's (1: nothing cut)."""
        sides = [max(r - left, b - t) for left, t, r, b in self.windows.values()]
        return sum(sides) / len(sides)

    def to_json(self) -> dict:
        return {"size": list(self.size), "windows": {name: list(w) for name, w in self.windows.items()}}

    @staticmethod
    def from_json(data: dict) -> "CropPlan":
        return CropPlan(
            size=(int(data["size"][0]), int(data["size"][1])),
            windows={name: tuple(float(v) for v in w) for name, w in data["windows"].items()},
        )


def object_box(points: Tensor, camera: Camera, quantile: float) -> Tensor | None:
    """The pixel box [4] (left, top, right, bottom) of `points` [P, 3] in `camera` between the `quantile` and
    1 - `quantile` of their pixel coordinates; None when fewer than MIN_POINTS lie in front of it."""
    pixels, depth = camera.project(points.to(camera.device, torch.float32))
    pixels = pixels[depth > 0]
    if len(pixels) < MIN_POINTS:
        return None
    low = torch.quantile(pixels.double(), quantile, dim=0)
    high = torch.quantile(pixels.double(), 1.0 - quantile, dim=0)
    return torch.cat([low, high]).cpu()


def crop_window(box: Tensor | None, width: int, height: int, margin: float, min_side: float) -> tuple:
    """The window (fractions of the frame: left, top, right, bottom) of a `width` x `height` frame around the pixel
    box `box` [4] grown by `margin` on each side, with the frame's aspect ratio and at least `min_side` (a fraction
    of the frame's side) wide, moved inside the frame; the whole frame when the box is None or does not fit."""
    if box is None:
        return WHOLE_FRAME
    left, top, right, bottom = box.tolist()
    centre_x, centre_y = (left + right) / 2 / width, (top + bottom) / 2 / height
    grow = 1.0 + 2.0 * margin
    side = max(grow * (right - left) / width, grow * (bottom - top) / height, min_side)  # same fraction on both axes
    if side >= 1.0:
        return WHOLE_FRAME
    x0 = min(max(centre_x - side / 2, 0.0), 1.0 - side)
    y0 = min(max(centre_y - side / 2, 0.0), 1.0 - side)
    return (x0, y0, x0 + side, y0 + side)


def read_crop_record(folder: Path, key: str, parse):
    """`parse` of entry `key` of the crop record a run's crop stage wrote in `folder` (RUN/crop); None when there is
    no record or the entry is null. A record that cannot be read is a one-line error naming it."""
    path = Path(folder) / CROP_FILE
    if not path.exists():
        return None
    try:
        value = read_json(path)[key]
        return None if value is None else parse(value)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        problem = f"is not a crop record ({type(exc).__name__}: {exc})"
        raise file_error(path, problem, "delete it to cut the photos again") from None


def read_crop_plan(folder: Path) -> CropPlan | None:
    """The plan a run's crop stage wrote in `folder` (RUN/crop); None when it has none or cut nothing."""
    return read_crop_record(folder, "plan", CropPlan.from_json)
