"""Spatially varying PBR materials from seeded procedural patterns, and their UV textures.

An object's material is a function of the world position (so it is continuous across UV seams and
across the parts of a composite): Voronoi cells split the surface into regions (large scale); each
region mixes two materials A and B by a pattern of its own — plain, stripes or noise blotches
(medium scale) — and a fine fractal noise varies colour and roughness inside (small scale);
optionally thin grout lines run along the cell borders.

Roughness is the perceptual roughness r of Mitsuba's principled BSDF (GGX alpha = r^2); the regions
span mirror-like (0.05) to rough (1.0). Metallic is 0 or 1 per material, sometimes in between.
Textures are baked by evaluating the material at the surface point of every texel centre.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np
import torch

from matspray.errors import ConfigError
from matspray.gltf.sample import apply_uv_transform, sample_texture, wrap_index
from matspray.synth.noise import ValueNoise, fbm, voronoi
from matspray.synth.shapes import Part

PATTERNS = ("plain", "stripes", "noise")
MIN_ROUGHNESS, MAX_ROUGHNESS = 0.05, 1.0
TEXTURE_HEIGHT = 256  # texture rows per part; textures are twice as wide (u runs around the part)


@dataclass
class Layer:
    """One homogeneous material: linear base colour, perceptual roughness, metallic."""

    base_color: np.ndarray  # [3] linear RGB
    roughness: float
    metallic: float

    def to_json(self) -> dict:
        return {
            "base_color": [round(float(c), 6) for c in self.base_color],
            "roughness": self.roughness,
            "metallic": self.metallic,
        }


@dataclass
class Region:
    """A Voronoi cell: layers A and B mixed by a pattern (mask 0 -> A, 1 -> B)."""

    a: Layer
    b: Layer
    pattern: str  # one of PATTERNS
    direction: np.ndarray  # [3] unit, stripe normal
    frequency: float  # stripes per unit length, or noise frequency
    threshold: float  # noise level above which B shows

    def to_json(self) -> dict:
        return {
            "a": self.a.to_json(),
            "b": self.b.to_json(),
            "pattern": self.pattern,
            "direction": self.direction.tolist(),
            "frequency": self.frequency,
            "threshold": self.threshold,
        }


@dataclass
class Material:
    sites: np.ndarray  # [S, 3] Voronoi sites, one per region
    regions: list[Region]
    grout: Layer | None  # material of the lines along cell borders, or None
    grout_width: float  # border half-width in units of the Voronoi gap
    detail: ValueNoise  # fine noise for colour and roughness variation
    blotches: ValueNoise  # medium noise for the "noise" pattern

    def to_json(self) -> dict:
        return {
            "sites": np.round(self.sites, 6).tolist(),
            "regions": [r.to_json() for r in self.regions],
            "grout": None if self.grout is None else self.grout.to_json(),
            "grout_width": self.grout_width,
        }


# ------------------------------------------------------------------------------------------ random materials
def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def random_color(rng: np.random.Generator, metal: bool) -> np.ndarray:  # [3] linear
    """A colour chosen in sRGB HSV: metals bright and mostly desaturated, dielectrics anything not near-black."""
    hue = rng.uniform()
    if metal:
        saturation, value = rng.uniform(0.0, 0.6), rng.uniform(0.65, 0.97)
    else:
        saturation, value = rng.uniform(0.15, 0.9), rng.uniform(0.2, 0.95)
    return srgb_to_linear(np.array(colorsys.hsv_to_rgb(hue, saturation, value)))


def random_metallic(rng: np.random.Generator) -> float:
    draw = rng.uniform()
    return 1.0 if draw < 0.4 else (0.0 if draw < 0.85 else round(float(rng.uniform(0.3, 0.7)), 3))


def random_layer(rng: np.random.Generator, roughness: float, metallic: float) -> Layer:
    return Layer(random_color(rng, metallic >= 0.5), round(float(roughness), 4), float(metallic))


def spread_roughness(rng: np.random.Generator, count: int) -> np.ndarray:  # [count] in [0.05, 1], shuffled
    """One value per stratum of [0.05, 1]: the first is mirror-like, the last fully rough."""
    edges = np.linspace(MIN_ROUGHNESS, MAX_ROUGHNESS, count + 1)
    values = rng.uniform(edges[:-1], edges[1:])
    values[0], values[-1] = MIN_ROUGHNESS, MAX_ROUGHNESS
    return rng.permutation(values)


def random_material(rng: np.random.Generator, regions: int | None = None) -> Material:
    """Seeded material with 3-5 regions. The regions' A layers (which always show; B only where the
    pattern puts it) include a mirror-like and a fully rough one, a metal (1) and a dielectric (0)."""
    count = int(regions if regions is not None else rng.integers(3, 6))
    roughness_a = spread_roughness(rng, count)
    metallic_a = rng.permutation([1.0, 0.0] + [random_metallic(rng) for _ in range(count - 2)])
    sites = rng.normal(size=(count, 3))
    sites = 0.8 * sites / np.linalg.norm(sites, axis=1, keepdims=True)
    region_list = []
    for k in range(count):
        direction = rng.normal(size=3)
        region_list.append(
            Region(
                a=random_layer(rng, roughness_a[k], metallic_a[k]),
                b=random_layer(rng, rng.uniform(MIN_ROUGHNESS, MAX_ROUGHNESS), random_metallic(rng)),
                pattern=PATTERNS[k] if k < len(PATTERNS) else str(rng.choice(PATTERNS)),
                direction=direction / np.linalg.norm(direction),
                frequency=float(rng.uniform(2.0, 6.0)),
                threshold=float(rng.uniform(-0.1, 0.2)),
            )
        )
    grout = random_layer(rng, rng.uniform(0.5, 0.9), 0.0) if rng.uniform() < 0.5 else None
    return Material(sites, region_list, grout, float(rng.uniform(0.03, 0.06)), ValueNoise(rng), ValueNoise(rng))


# ------------------------------------------------------------------------------------------ evaluation
def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def pattern_mask(region: Region, material: Material, points: np.ndarray) -> np.ndarray:  # [N, 3] -> [N] in [0, 1]
    if region.pattern == "stripes":
        wave = np.sin(2.0 * np.pi * region.frequency * (points @ region.direction))
        return smoothstep(-0.15, 0.15, wave)
    if region.pattern == "noise":
        level = fbm(material.blotches, points, region.frequency, octaves=3)
        return smoothstep(region.threshold - 0.04, region.threshold + 0.04, level)
    return np.zeros(len(points))


def evaluate_material(material: Material, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Material at world points [N, 3] -> base colour [N, 3] linear, roughness [N], metallic [N]."""
    cell, gap = voronoi(points, material.sites)
    base = np.zeros((len(points), 3))
    rough = np.zeros(len(points))
    metal = np.zeros(len(points))
    for k, region in enumerate(material.regions):
        inside = cell == k
        if not inside.any():
            continue
        m = pattern_mask(region, material, points[inside])
        base[inside] = (1 - m)[:, None] * region.a.base_color + m[:, None] * region.b.base_color
        rough[inside] = (1 - m) * region.a.roughness + m * region.b.roughness
        metal[inside] = (1 - m) * region.a.metallic + m * region.b.metallic
    detail = fbm(material.detail, points, 12.0, octaves=3)  # [N] in [-1, 1], fine scale
    base = base * (1.0 + 0.15 * detail)[:, None]
    rough = rough + 0.05 * detail
    if material.grout is not None:
        line = 1.0 - smoothstep(material.grout_width, 1.5 * material.grout_width, gap)  # 1 on borders
        base = (1 - line)[:, None] * base + line[:, None] * material.grout.base_color
        rough = (1 - line) * rough + line * material.grout.roughness
        metal = (1 - line) * metal + line * material.grout.metallic
    return np.clip(base, 0.0, 1.0), np.clip(rough, MIN_ROUGHNESS, MAX_ROUGHNESS), np.clip(metal, 0.0, 1.0)


# ------------------------------------------------------------------------------------------ textures
@dataclass(frozen=True)
class Sampling:
    """How a texture is read at a mesh's UV: an affine map of the UV first (glTF's KHR_texture_transform),
    then a bilinear lookup wrapped per axis ('repeat', 'clamp' or 'mirror')."""

    to_uv: np.ndarray | None = None  # [3, 3] acting on (u, v, 1); None: identity
    wrap_s: str = "repeat"  # along u
    wrap_t: str = "repeat"  # along v


@dataclass
class Textures:
    """A part's material in UV space (row 0 at v = 0, texel centres at +0.5, like Mitsuba). Procedural
    textures are [T, 2T] and repeat; a glTF asset's have any size and their file's `Sampling`
    (roughness and metallic share one, as they share the metallic-roughness texture)."""

    base_color: np.ndarray  # [T, W, 3] linear
    roughness: np.ndarray  # [T', W']
    metallic: np.ndarray  # [T', W']
    base_color_sampling: Sampling = Sampling()
    metallic_roughness_sampling: Sampling = Sampling()
    double_sided: bool = False  # shade back faces too (glTF doubleSided); procedural parts are closed


def texel_uvs(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:  # -> u [T, W], v [T, W]
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    return np.meshgrid(u, v, indexing="xy")


def bake_textures(material: Material, part: Part, height: int = TEXTURE_HEIGHT) -> Textures:
    u, v = texel_uvs(height, 2 * height)
    points = part.surface(u, v).reshape(-1, 3)
    base, rough, metal = evaluate_material(material, points)
    shape = (height, 2 * height)
    return Textures(
        base.reshape(*shape, 3).astype(np.float32),
        rough.reshape(shape).astype(np.float32),
        metal.reshape(shape).astype(np.float32),
    )


def texture_lookup(texture: np.ndarray, uv: np.ndarray, sampling: Sampling = Sampling()) -> np.ndarray:
    """Bilinear lookup as Mitsuba's bitmap texture does it (matspray.gltf.sample_texture, in float64).

    texture: [T, W] or [T, W, C], uv: [N, 2] -> [N] or [N, C]
    """
    values = torch.from_numpy(np.asarray(texture, dtype=np.float64))
    to_uv = None if sampling.to_uv is None else torch.from_numpy(np.asarray(sampling.to_uv, dtype=np.float64))
    looked_up = sample_texture(
        values.reshape(*values.shape[:2], -1),
        torch.from_numpy(np.asarray(uv, dtype=np.float64)),
        sampling.wrap_s,
        sampling.wrap_t,
        to_uv,
    )
    return looked_up.numpy().reshape(len(uv), *texture.shape[2:])


MAX_UNWRAPPED = 8192  # texels per axis of a texture unwrapped for one wrap mode


def single_wrap(texture: np.ndarray, sampling: Sampling, uvs: np.ndarray) -> tuple[np.ndarray, Sampling]:
    """The same lookup as (texture, sampling) over the UVs [V, 2] of a mesh, with one wrap mode for both axes
    (Mitsuba's bitmap texture has one): with two different modes, the texels that the mesh's UV range
    reaches (and one more each side) are laid out explicitly and read with 'clamp'. Bilinear weights
    and neighbours stay those of the original lookup, so the values are identical."""
    if sampling.wrap_s == sampling.wrap_t:
        return texture, sampling
    height, width = texture.shape[:2]
    to_uv = np.eye(3) if sampling.to_uv is None else np.asarray(sampling.to_uv, dtype=np.float64)
    uv = apply_uv_transform(torch.from_numpy(np.asarray(uvs, dtype=np.float64)), torch.from_numpy(to_uv)).numpy()
    low = np.floor(uv.min(0) * [width, height] - 0.5).astype(np.int64) - 1  # [2] first texel reached, x and y
    high = np.ceil(uv.max(0) * [width, height] - 0.5).astype(np.int64) + 1
    if (high - low + 1 > MAX_UNWRAPPED).any():
        raise ConfigError(
            f"a texture with wraps {sampling.wrap_s}/{sampling.wrap_t} is tiled over "
            f"{(high - low + 1).tolist()} texels; "
            f"at most {MAX_UNWRAPPED} per axis are supported"
        )
    xs = wrap_index(torch.arange(low[0], high[0] + 1), width, sampling.wrap_s).numpy()
    ys = wrap_index(torch.arange(low[1], high[1] + 1), height, sampling.wrap_t).numpy()
    unwrapped = np.ascontiguousarray(texture[ys][:, xs])
    # u' W' - 0.5 = u W - 0.5 - low_x: the texel that was x is now x - low_x
    size = np.array([len(xs), len(ys)], dtype=np.float64)
    shift = np.array(
        [[width / size[0], 0.0, -low[0] / size[0]], [0.0, height / size[1], -low[1] / size[1]], [0.0, 0.0, 1.0]]
    )
    return unwrapped, Sampling(shift @ to_uv, "clamp", "clamp")


def bilinear_lookup(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:  # [T, W, ...], [N, 2] -> [N, ...]
    """The repeating, untransformed lookup of procedural textures."""
    return texture_lookup(texture, uv)


# ------------------------------------------------------------------------------------------ table-top captures
# (linear RGB) an object's tone on a table: a bone-white object (its shadowed side is a dark grey, close to the dark
# wooden table's colour) or a dark one on a light table; each keeps its pattern as a small variation of brightness
TONES = {"white-on-dark": ((0.62, 0.3), (1.0, 0.96, 0.88)), "dark-on-light": ((0.03, 0.07), (1.0, 0.92, 0.85))}
TABLES = {"white-on-dark": (0.16, 0.1, 0.06), "dark-on-light": (0.62, 0.52, 0.4)}  # the tables' mean colours
TABLE_TEXELS = 512


def toned(textures: Textures, tabletop: str) -> Textures:
    """`textures` in the tone of `tabletop`'s object (TONES): dielectric, its base colour's luminance mapped to a
    narrow band of brightness (offset + scale * luminance) times one tint."""
    (offset, scale), tint = TONES[tabletop]
    luminance = textures.base_color.mean(axis=-1, keepdims=True)  # [T, W, 1]
    base = (offset + scale * luminance) * np.asarray(tint)
    return Textures(base, textures.roughness, np.zeros_like(textures.metallic), double_sided=textures.double_sided)


def table_texture(tabletop: str, seed: int, texels: int = TABLE_TEXELS) -> np.ndarray:  # -> [T, T, 3] linear
    """A wooden table's base colour: grain (stripes bent by fractal noise) and blotches around TABLES' colour."""
    noise = ValueNoise(np.random.default_rng([seed, 7]))
    v, u = np.meshgrid((np.arange(texels) + 0.5) / texels, (np.arange(texels) + 0.5) / texels, indexing="ij")
    points = np.stack([u, v, np.zeros_like(u)], axis=-1)
    grain = 0.5 + 0.5 * np.sin(2.0 * np.pi * (60.0 * u + 3.0 * fbm(noise, points, 4.0)))
    blotch = fbm(noise, points + 5.0, 12.0)
    brightness = 0.75 + 0.35 * grain + 0.25 * blotch  # [T, T] about 1
    return (brightness[..., None] * np.asarray(TABLES[tabletop])).clip(0.0, 1.0)
