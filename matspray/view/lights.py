"""The lights the viewer offers, loaded the way `matspray relight` loads them, and turned about the up axis.

Choices: the run's estimated light (the shown variant's `envmap.exr`), the named lights (the built-ins and the packaged
HDRIs, the set `matspray relight --help` lists), every HDRI given with
`--env` (files, or folders of .exr/.hdr files) and files uploaded from the page. A light is loaded with
`lights.load_envmap`, brought to `ENV_HEIGHT` rows and prefiltered once, exactly as `relight` does with its default
`--env-height`, so that the viewer's picture is the picture `relight` writes.

Turning the light is not a new light: `RotatedLight` turns the directions the shading looks up by the opposite angle,
so a turn costs nothing but a 3 x 3 rotation per lookup, and at 0 degrees the lookups are the unturned ones, bit for
bit.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from matspray.data.images import HDR_SUFFIXES
from matspray.errors import DataError, MatsprayError, file_error
from matspray.method.asset import ENVMAP_FILE
from matspray.render.shade.envmap import EnvironmentMap, PrefilteredEnvironment, sample_latlong
from matspray.render.shade.latlong import pixel_directions
from matspray.render.shade.light import PrefilteredLight
from matspray.render.shade.lights import list_envmaps, load_envmap

ENV_HEIGHT = 64  # `matspray relight --env-height` default
ESTIMATED = "estimated (run)"  # the label of the run's own light
CACHED_LIGHTS = 8  # prefiltered lights kept in memory, so switching back and forth does not reload


@dataclass(frozen=True)
class LightChoice:
    """One entry of the light menu: what it reads (a built-in name, a file, or None for the run's estimated light)."""

    label: str
    spec: str | None


def rotate_about_up(directions: Tensor, angle: float) -> Tensor:  # [..., 3] -> [..., 3]
    """Directions turned by `angle` radians about the world up axis (+z), counter-clockwise seen from above."""
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = directions.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1)


class RotatedLight(PrefilteredLight):
    """An environment light turned by `angle` radians about the up axis: L'(d) = L(R(-angle) d). It answers every
    lookup `shade`, `background_radiance` and the shadow factors make (`lookup_specular`, `lookup_diffuse`,
    `radiance`, `map`, `source`), each by turning the direction back and asking the unturned light."""

    def __init__(self, light: EnvironmentMap, prefiltered: PrefilteredEnvironment, angle: float = 0.0):
        self.light, self.prefiltered, self.angle = light, prefiltered, float(angle)
        self._source: Tensor | None = None

    def _back(self, directions: Tensor) -> Tensor:
        return directions if self.angle == 0.0 else rotate_about_up(directions, -self.angle)

    @property
    def map(self) -> Tensor:  # [H, 2H, 3] the unturned map: callers read only its dtype and device
        return self.light.map

    @property
    def source(self) -> Tensor:  # [H, 2H, 3] the turned map itself, for the shadow factors (`render.visibility`)
        if self._source is None:
            if self.angle == 0.0:
                self._source = self.prefiltered.source if self.prefiltered.source is not None else self.light.map
            else:
                rows = self.light.height
                directions = pixel_directions(rows, 2 * rows, device=self.map.device, dtype=self.map.dtype)
                self._source = sample_latlong(self.light.map, self._back(directions))
        return self._source

    def radiance(self, directions: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
        return self.light.radiance(self._back(directions))

    def lookup_specular(self, directions: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
        return self.prefiltered.lookup_specular(self._back(directions), roughness)

    def lookup_diffuse(self, normals: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        return self.prefiltered.lookup_diffuse(self._back(normals))

    def turned(self, angle: float) -> "RotatedLight":
        """The same light at another angle (the prefiltering is shared)."""
        return RotatedLight(self.light, self.prefiltered, angle)


def light_choices(files, has_estimate: bool = True) -> list[LightChoice]:
    """The menu: the run's estimated light, the named lights, then the files (labelled by name, made unique)."""
    choices = [LightChoice(ESTIMATED, None)] if has_estimate else []
    choices += [LightChoice(name, name) for name in list_envmaps()]
    for path in files:
        choices.append(LightChoice(unique_label(path.name, [c.label for c in choices]), str(path)))
    return choices


def unique_label(name: str, taken) -> str:
    taken = set(taken)
    label, k = name, 2
    while label in taken:
        label, k = f"{name} ({k})", k + 1
    return label


class LightLoader:
    """Loads lights as `relight` does and keeps the last few prefiltered, keyed by what was read."""

    def __init__(self, device="cpu", height: int = ENV_HEIGHT):
        self.device, self.height = torch.device(device), height
        self._cache: OrderedDict[str, RotatedLight] = OrderedDict()

    def load(self, spec: str | Path) -> RotatedLight:
        """The light of a named light or a .exr/.hdr path (unturned). Raises MatsprayError with a one-line message
        naming the file when it cannot be read, is no HDR file, or holds no lat-long map."""
        key = str(spec)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        path = Path(key)
        if key not in list_envmaps() and path.suffix.lower() not in HDR_SUFFIXES:
            raise file_error(
                path,
                f"is not an HDR light ('{path.suffix or 'no suffix'}'); a light is a lat-long .exr or .hdr file",
                "the viewer keeps the last light",
            )
        try:
            _, env_map = load_envmap(key)
            light = EnvironmentMap.from_tensor(
                env_map.to(self.device), height=self.height, learnable=False, what=f"{path.name}"
            )
        except MatsprayError as exc:
            message = str(exc)
            raise DataError(message if message.startswith(str(path)) else f"{path}: {message}") from None
        except (OSError, ValueError, RuntimeError) as exc:  # a reader's own failure on a corrupt file
            raise file_error(
                path, f"cannot be read as an HDR image ({type(exc).__name__}: {' '.join(str(exc).split())[:160]})"
            ) from None
        with torch.no_grad():
            loaded = RotatedLight(light, light.prefilter())
        self._cache[key] = loaded
        while len(self._cache) > CACHED_LIGHTS:
            self._cache.popitem(last=False)
        return loaded


def estimated_light_path(asset_folder: Path) -> Path | None:
    """The run's light for one variant's asset folder (`envmap.exr`), or None when that variant learned none."""
    path = Path(asset_folder) / ENVMAP_FILE
    return path if path.is_file() else None
