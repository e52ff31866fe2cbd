"""A light that moves with the camera: a flash at each photo's camera centre, learned beside the environment.

Photos taken with a flash are lit by two lights: the room (one environment for every photo) and the flash, which
sits on the camera and so lights each photo from where it was taken. An environment alone cannot explain that light;
refinement then bakes the flash's shading into the materials, and the asset relights softly wrong. With a camera
light, refinement adds, to each flash photo's split-sum shading, a point light at its camera's centre:

    L_flash = I (d0 / d)^2 f_r(wo, wo) (n.wo)        (`brdf.camera_light_radiance`)

I is a learnable RGB intensity (its log, so it stays positive), d a pixel's distance to the camera (the frozen
Gaussians' blended distance) and d0 a reference distance (the training cameras' mean distance to the object's centre)
that keeps I near the scale of the environment's radiance. The intensity is saved with the asset
(`CAMERA_LIGHT_FILE`): scoring held-out flash photos needs it; relighting under another light leaves it out.

Which photos had a flash: the EXIF of each photo (`refine.camera_light` "auto"), every photo ("on"), none ("off").
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from torch import Tensor, nn

from matspray.data.images import flash_fired
from matspray.errors import SettingError, file_error
from matspray.rundir import write_json

CAMERA_LIGHT_FILE = "camera_light.json"
CAMERA_LIGHT_FORMAT = "matspray-camera-light-1"
CAMERA_LIGHT_MODES = ("auto", "on", "off")
MIN_DISTANCE_SHARE = 1e-2  # of d0: a pixel the Gaussians barely cover has no distance worth the name


def check_mode(mode: str) -> None:
    if mode not in CAMERA_LIGHT_MODES:
        raise SettingError("camera_light", f"unknown mode '{mode}'; choose one of {', '.join(CAMERA_LIGHT_MODES)}")


def lit_views(mode: str, paths: list) -> list[bool]:
    """Which views a camera light lights under `mode` ("auto": those whose photo says its flash fired), from the
    views' photo files (None for a view without a file)."""
    check_mode(mode)
    if mode == "off":
        return [False] * len(paths)
    if mode == "on":
        return [True] * len(paths)
    return [flash_fired(path) for path in paths]


def falloff(distance: Tensor, alpha: Tensor, reference: float) -> Tensor:  # [H, W], [H, W] coverage -> [H, W, 1]
    """(d0 / d)^2 per pixel from the blended distance over the coverage; where nothing covers a pixel (its shading
    is multiplied by a coverage of 0 anyway), d = d0."""
    covered = alpha > 1e-3
    d = torch.where(covered, distance / alpha.clamp_min(1e-3), torch.full_like(distance, reference))
    return ((reference / d.clamp_min(MIN_DISTANCE_SHARE * reference)) ** 2)[..., None]


class CameraLight(nn.Module):
    """The flash's RGB intensity (learnable unless `fixed()`) and its reference distance d0."""

    def __init__(self, intensity: Tensor, reference_distance: float, views: str = "auto"):  # intensity [3] > 0
        super().__init__()
        if not (math.isfinite(reference_distance) and reference_distance > 0):
            raise ValueError(f"camera light: the reference distance must be finite and > 0, got {reference_distance}")
        self.log_intensity = nn.Parameter(torch.as_tensor(intensity, dtype=torch.float32).clamp_min(1e-8).log())
        self.reference_distance = float(reference_distance)
        self.views = views  # which views it lights, as `lit_views` reads it: "auto" or "on"

    @property
    def intensity(self) -> Tensor:  # [3]
        return self.log_intensity.exp()

    @classmethod
    def initial(cls, value: float, reference_distance: float, views: str, device=None) -> CameraLight:
        return cls(torch.full((3,), float(value)), reference_distance, views).to(device)

    def fixed(self) -> CameraLight:
        light = CameraLight(self.intensity.detach().cpu(), self.reference_distance, self.views)
        return light.requires_grad_(False).to(self.log_intensity.device)

    def save(self, path) -> None:
        record = {
            "format": CAMERA_LIGHT_FORMAT,
            "intensity": [float(x) for x in self.intensity.detach().cpu()],
            "reference_distance": self.reference_distance,
            "views": self.views,
        }
        write_json(Path(path), record)

    @classmethod
    def load(cls, path) -> CameraLight:
        path = Path(path)
        hint = "delete it to score the asset without its camera light"
        try:
            record = json.loads(path.read_text())
            intensity = [float(x) for x in record["intensity"]]
            distance = float(record["reference_distance"])
            views = record.get("views", "auto")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise file_error(path, f"is not a MatSpray camera light ({exc.__class__.__name__})", hint) from None
        if record.get("format") != CAMERA_LIGHT_FORMAT or len(intensity) != 3 or views not in ("auto", "on"):
            raise file_error(path, f"is not a {CAMERA_LIGHT_FORMAT} file with 3 intensities", hint)
        if not all(math.isfinite(x) and x >= 0 for x in [*intensity, distance]) or distance <= 0:
            raise file_error(path, "holds a negative, zero or non-finite intensity or distance", hint)
        return cls(torch.tensor(intensity), distance, views).requires_grad_(False)


def lighting(camera_light: CameraLight | None, path) -> CameraLight | None:
    """`camera_light` if it lit the photo at `path` (as refinement lit its training photos: `lit_views`), else None."""
    return camera_light if camera_light is not None and lit_views(camera_light.views, [path])[0] else None


def reference_distance(cameras: list, bounds: Tensor) -> float:  # bounds [2, 3] the object's box
    """d0: the cameras' mean distance to the centre of the object's box."""
    centre = bounds.double().mean(0).cpu()
    return float(torch.stack([c.center.double().cpu() - centre for c in cameras]).norm(dim=-1).mean())
