"""Environment maps for the whole project: built-in procedural lights, HDRI files, lookups.

Every map is a lat-long tensor [H, 2H, 3] of linear RGB radiance in the convention of
`matspray.render.shade.latlong` (world up +z, row 0 straight up). `load_envmap` resolves a name or a path:

1. a built-in procedural map (`sky`, `studio`, `sunset`, `overcast`), made at any height;
2. a path to a `.exr` / `.hdr` file;
3. the name of an HDRI that ships in the package (`matspray/hdri/`: six CC0 Poly Haven maps, city, forest,
   interior, studio-small, sunrise, venice-sunset; THIRD_PARTY_NOTICES.md).

No name means two lights (`matspray.presets.BUILTIN_LIGHTS` and the packaged files' stems differ; a test checks).

A file's radiance must be physical: NaN and Inf are refused in one line naming the file, and so is a map whose
negative values carry more than NEGATIVE_ENERGY_SHARE of its energy. Less than that is a lossy codec's ringing next
to dark pixels: it is clamped to 0, with one notice line naming the file, the count and the share.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from matspray.data.images import HDR_SUFFIXES, read_raw, resize
from matspray.errors import ConfigError, DataError, file_error
from matspray.presets import BUILTIN_LIGHTS, HDRI_FOLDER
from matspray.render.shade.latlong import direction_to_uv, pixel_directions, pixel_solid_angles

DEFAULT_HEIGHT = 128  # working size for rendering: 128 x 256
BUILTIN_HEIGHT = 256  # when a caller asks for a built-in map at "native" size
SUPERSAMPLES = 4  # built-ins are averaged over 4 x 4 directions per pixel (small suns stay exact)
# Lossy EXR codecs (DWAA/DWAB) ring a little below zero next to dark pixels. How far below zero depends on the
# bright pixels beside the dark ones, not on the map's mean (a night map rings as deep as a day map, with a mean a
# hundred times lower), so a tolerance in values refuses dark maps. What the ringing never is, is energy: a map whose
# negative values (weighted by solid angle) hold more than this share of its total |radiance| is not a light.
NEGATIVE_ENERGY_SHARE = 1e-3


# ------------------------------------------------------------------------------------------ helpers
def smoothstep(edge0: float, edge1: float, x: Tensor) -> Tensor:  # [...] -> [...]
    t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def direction_from_angles(azimuth_deg: float, elevation_deg: float) -> Tensor:  # [3] unit, z up
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)], dtype=torch.float64)


def colour(r: float, g: float, b: float) -> Tensor:  # [3]
    return torch.tensor([r, g, b], dtype=torch.float64)


def sun_disc(d: Tensor, sun: Tensor, radius_deg: float, glow_deg: float) -> tuple[Tensor, Tensor]:
    """Disc mask [...] (soft edge a tenth of the radius wide) and a Gaussian glow [...] around `sun`."""
    angle = torch.acos((d @ sun).clamp(-1.0, 1.0))  # [...] radians
    radius = math.radians(radius_deg)
    disc = 1.0 - smoothstep(0.9 * radius, 1.1 * radius, angle)
    glow = torch.exp(-0.5 * (angle / math.radians(glow_deg)) ** 2)
    return disc, glow


def soft_box(d: Tensor, azimuth_deg: float, elevation_deg: float, width_deg: float, height_deg: float) -> Tensor:
    """Mask [...] of a rectangular light seen from the centre, soft over 3 degrees at its edges."""
    az = torch.rad2deg(torch.atan2(d[..., 1], d[..., 0]))
    el = torch.rad2deg(torch.asin(d[..., 2].clamp(-1.0, 1.0)))
    daz = torch.remainder(az - azimuth_deg + 180.0, 360.0) - 180.0
    daz = daz * torch.cos(torch.deg2rad(el))  # angular width shrinks towards the poles
    inside_w = 1.0 - smoothstep(0.5 * width_deg - 1.5, 0.5 * width_deg + 1.5, daz.abs())
    inside_h = 1.0 - smoothstep(0.5 * height_deg - 1.5, 0.5 * height_deg + 1.5, (el - elevation_deg).abs())
    return inside_w * inside_h


def sky_gradient(z: Tensor, zenith: Tensor, horizon: Tensor, ground: Tensor) -> Tensor:  # [...] -> [..., 3]
    """Sky from horizon to zenith colour above z = 0, a flat ground colour below, blended over ~3 degrees."""
    up = z.clamp_min(0.0)[..., None]
    sky = horizon + (zenith - horizon) * (1.0 - (1.0 - up) ** 3)
    blend = smoothstep(-0.05, 0.05, z)[..., None]
    return ground + (sky - ground) * blend


# ------------------------------------------------------------------------------------------ built-ins
def sky_radiance(d: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
    """Clear day: blue gradient, warm-grey ground, a sun 40 degrees up (~70% of the irradiance)."""
    base = sky_gradient(d[..., 2], colour(0.12, 0.25, 0.6), colour(0.65, 0.72, 0.85), colour(0.2, 0.17, 0.13))
    disc, glow = sun_disc(d, direction_from_angles(35.0, 40.0), radius_deg=2.5, glow_deg=8.0)
    return base + disc[..., None] * colour(600.0, 560.0, 500.0) + glow[..., None] * colour(0.8, 0.7, 0.5)


def studio_radiance(d: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
    """Dark room with a warm key soft box, a cool fill, a rim light behind and a faint floor bounce."""
    z = d[..., 2]
    room = torch.where(z < 0.0, 0.05, 0.025)[..., None] * colour(1.0, 1.0, 1.0)
    key = soft_box(d, 40.0, 30.0, 45.0, 35.0)[..., None] * colour(7.0, 6.3, 5.4)
    fill = soft_box(d, -70.0, 10.0, 30.0, 45.0)[..., None] * colour(1.6, 1.9, 2.4)
    rim = soft_box(d, 170.0, 55.0, 60.0, 20.0)[..., None] * colour(4.0, 4.0, 4.0)
    return room + key + fill + rim


def sunset_radiance(d: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
    """Low orange sun 6 degrees above the horizon under a deep blue zenith, dark ground."""
    base = sky_gradient(d[..., 2], colour(0.1, 0.14, 0.4), colour(2.0, 0.9, 0.36), colour(0.12, 0.09, 0.07))
    disc, glow = sun_disc(d, direction_from_angles(200.0, 6.0), radius_deg=3.0, glow_deg=15.0)
    return base + disc[..., None] * colour(750.0, 425.0, 200.0) + glow[..., None] * colour(3.0, 1.2, 0.4)


def overcast_radiance(d: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
    """Uniformly clouded sky (CIE overcast: three times brighter at the zenith than at the horizon)."""
    z = d[..., 2]
    sky = (1.0 + 2.0 * z.clamp_min(0.0))[..., None] * colour(0.43, 0.43, 0.45)
    ground = colour(0.2, 0.19, 0.18)
    blend = smoothstep(-0.05, 0.05, z)[..., None]
    return ground + (sky - ground) * blend


BUILTINS: dict[str, Callable[[Tensor], Tensor]] = dict(
    zip(BUILTIN_LIGHTS, (sky_radiance, studio_radiance, sunset_radiance, overcast_radiance), strict=True)
)
# Preference order for relighting lights that differ from a training light.
RELIGHT_PREFERENCE = ("studio", "sunset", "sky", "overcast")


def builtin_envmap(name: str, height: int = DEFAULT_HEIGHT) -> Tensor:  # [H, 2H, 3] float32
    """A built-in map, each pixel the mean radiance over a 4 x 4 grid of directions inside it."""
    if name not in BUILTINS:
        raise ConfigError(f"unknown built-in environment map '{name}' (built-ins: {', '.join(BUILTINS)})")
    check_height(height)
    s = SUPERSAMPLES
    fine = pixel_directions(height * s, 2 * height * s, dtype=torch.float64)  # [sH, 2sH, 3]
    radiance = BUILTINS[name](fine)  # [sH, 2sH, 3]
    return radiance.reshape(height, s, 2 * height, s, 3).mean(dim=(1, 3)).float()


def default_relight_names(train_name: str, count: int = 2) -> list[str]:
    """The first `count` built-ins of RELIGHT_PREFERENCE that are not the training light."""
    return [name for name in RELIGHT_PREFERENCE if name != train_name][:count]


# ------------------------------------------------------------------------------------------ files
def hdri_folders() -> list[Path]:
    """The folders whose .exr / .hdr files are named lights: the package's own."""
    return [HDRI_FOLDER] if HDRI_FOLDER.is_dir() else []


def hdri_files() -> dict[str, Path]:
    """Name (file stem) -> path of every .exr / .hdr in the packaged HDRI folder."""
    files: dict[str, Path] = {}
    for folder in hdri_folders():
        for path in sorted(folder.iterdir()):
            if path.suffix.lower() in HDR_SUFFIXES and path.stem not in files:
                files[path.stem] = path
    return files


def list_envmaps() -> list[str]:
    """Every name `load_envmap` accepts besides paths: built-ins, then the packaged HDRI files."""
    return list(BUILTINS) + [name for name in hdri_files() if name not in BUILTINS]


def envmap_name(path: Path) -> str:
    """A file-name-safe name for a map read from `path`: its stem, lower case, runs of odd characters as '-'."""
    name = re.sub(r"[^a-z0-9_]+", "-", path.stem.lower()).strip("-")
    return name or "envmap"


def read_envmap_file(path: Path, height: int | None = DEFAULT_HEIGHT) -> Tensor:  # [H, 2H, 3] float32
    """Read a lat-long .exr/.hdr, check it is 2:1, clamp negative values, resample to `height` rows."""
    path = Path(path)
    if path.suffix.lower() not in HDR_SUFFIXES:
        raise file_error(path, f"an environment map must be .exr or .hdr, not '{path.suffix}'", "convert it to OpenEXR")
    values = read_raw(path)  # DataError when unreadable
    if values.shape[-1] < 3:
        values = values[..., :1].expand(-1, -1, 3)
    rows, cols = values.shape[:2]
    if rows == 0 or cols != 2 * rows:
        raise file_error(
            path,
            f"is {cols}x{rows} pixels but a lat-long environment map is twice as wide as tall",
            "use an equirectangular (lat-long) panorama",
        )
    env = physical_radiance(path, values[..., :3]).contiguous()
    if height is not None and height != rows:
        check_height(height)
        env = resize(env, height, 2 * height, mode="area").clamp_min(0.0)
    return env.float()


def negative_energy(rgb: Tensor) -> tuple[int, float]:  # [H, W, 3] finite lat-long -> (count, share)
    """How many values are below zero, and the share of the map's energy they hold: sum over the negative values of
    |L| dw over the sum of |L| dw over all of them (dw: each pixel's solid angle; 0 for an all-black map)."""
    weights = pixel_solid_angles(rgb.shape[0], rgb.shape[1], device=rgb.device, dtype=torch.float64)[..., None]
    magnitude = rgb.double().abs() * weights
    negative = rgb < 0
    total = float(magnitude.sum())
    return int(negative.sum()), (float(magnitude[negative].sum()) / total if total > 0 else 0.0)


_NOTICED: set[str] = set()  # files whose ringing was reported: a light read twice is reported once


def physical_radiance(path: Path, rgb: Tensor) -> Tensor:  # [H, W, 3] -> [H, W, 3] >= 0
    """`rgb` with a codec's ringing clamped to 0 (one notice line per file), or a one-line DataError naming the file
    when it holds NaN, Inf or negative radiance beyond ringing (more than NEGATIVE_ENERGY_SHARE of its energy)."""
    finite = torch.isfinite(rgb)
    if not finite.all():  # read_raw refuses these already; a reader that does not must not pass them
        raise file_error(
            path, f"holds {int((~finite).sum())} NaN or Inf values", "re-export the map with finite values"
        )
    count, share = negative_energy(rgb)
    if count == 0:
        return rgb
    figures = f"{count} value{'s' * (count != 1)}, {100 * share:.3g} % of its energy, down to {float(rgb.min()):.3g}"
    if share > NEGATIVE_ENERGY_SHARE:
        raise file_error(
            path,
            f"holds negative radiance ({figures})",
            "a light is >= 0 everywhere: re-export the map without negative values",
        )
    if str(path) not in _NOTICED:
        _NOTICED.add(str(path))
        print(f"notice: {path}: {figures} below zero, a lossy codec's ringing, clamped to 0", file=sys.stderr)
    return rgb.clamp_min(0.0)


def check_height(height: int) -> None:
    if not isinstance(height, int) or not 4 <= height <= 8192:
        raise ConfigError(f"environment map height must be an integer in [4, 8192], got {height!r}")


def load_envmap(spec: str | Path, height: int | None = DEFAULT_HEIGHT) -> tuple[str, Tensor]:
    """Resolve a built-in name, a file path or a packaged HDRI name -> (name, map [H, 2H, 3] linear RGB).

    `height` is the working size in rows (None: a file's own size, 256 for built-ins).
    """
    text = str(spec)
    if text in BUILTINS:
        return text, builtin_envmap(text, BUILTIN_HEIGHT if height is None else height)
    path = Path(text).expanduser()
    if path.is_file():
        return envmap_name(path), read_envmap_file(path, height)
    if path.suffix.lower() in HDR_SUFFIXES and len(path.parts) > 1:
        raise file_error(path, "file does not exist")
    packaged = hdri_files()
    stem = path.stem if path.suffix.lower() in HDR_SUFFIXES else text
    if stem in packaged and (path.suffix == "" or packaged[stem].suffix.lower() == path.suffix.lower()):
        return envmap_name(packaged[stem]), read_envmap_file(packaged[stem], height)
    files_note = f"; HDRIs: {', '.join(sorted(packaged))}" if packaged else ""
    raise ConfigError(
        f"unknown environment map '{text}': not an existing .exr/.hdr file, nor a named light (built-ins: "
        f"{', '.join(BUILTINS)}{files_note})"
    )


# ------------------------------------------------------------------------------------------ lookup
def lookup_envmap(env: Tensor, directions: Tensor) -> Tensor:
    """Bilinear radiance lookup.

    env: Tensor,         # [H, W, C] lat-long map
    directions: Tensor,  # [..., 3] unit world directions (towards the light)
    returns              # [..., C]
    Pixel centres at +0.5, wrapping around in longitude, clamped at the poles.
    """
    height, width, channels = env.shape
    uv = direction_to_uv(directions.to(env.dtype))  # [..., 2]
    x = uv[..., 0] * width - 0.5
    y = (uv[..., 1] * height - 0.5).clamp(0.0, height - 1.0)
    x0, y0 = torch.floor(x), torch.floor(y)
    wx, wy = (x - x0)[..., None], (y - y0)[..., None]
    x0 = x0.long()
    y0 = y0.long().clamp(0, height - 1)
    x1, y1 = x0 + 1, (y0 + 1).clamp(max=height - 1)
    x0, x1 = torch.remainder(x0, width), torch.remainder(x1, width)
    top = env[y0, x0] * (1 - wx) + env[y0, x1] * wx
    bottom = env[y1, x0] * (1 - wx) + env[y1, x1] * wx
    return top * (1 - wy) + bottom * wy


def check_envmap(env: Tensor, what: str = "environment map") -> None:
    """Raise DataError unless `env` is a finite, non-negative [H, 2H, 3] tensor."""
    if env.ndim != 3 or env.shape[-1] != 3 or env.shape[1] != 2 * env.shape[0]:
        raise DataError(f"{what}: expected a lat-long map [H, 2H, 3], got shape {tuple(env.shape)}")
    if not torch.isfinite(env).all() or (env < 0).any():
        raise DataError(f"{what}: holds negative, NaN or Inf radiance")
