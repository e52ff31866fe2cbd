"""Mitsuba 3 scenes of a synthetic object: meshes, principled BSDFs fed by the baked textures, an
environment emitter in our lat-long convention, and cameras converted from ours.

Mitsuba is imported lazily (`select_variant` first), so the rest of the project runs without it.
"""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass, field

import numpy as np

from matspray.data.camera import Camera
from matspray.errors import ConfigError
from matspray.synth.materials import Sampling, Textures, single_wrap
from matspray.synth.shapes import Part

VARIANTS = ("llvm_ad_rgb", "scalar_rgb")  # preference order
GPU_VARIANT = "cuda_ad_rgb"  # tried first where torch sees a CUDA GPU (a paper-sized object renders there in minutes)
MAX_DEPTH = 8  # path length of the path tracer (bounces between parts of a composite need a few)
GROUND_BASE_COLOR, GROUND_ROUGHNESS = 0.3, 0.8  # the ground plane of unmasked captures: grey, rough, dielectric

# Our lat-long map (world +z up, u = atan2(y, -x) / 2pi + 0.5, v = acos(z) / pi) against Mitsuba's
# envmap (local +y up, u = atan2(x, -z) / 2pi, v = acos(y) / pi): the local direction of world d is
# (-d_y, d_z, -d_x), so the emitter's to_world (local -> world) is this rotation's transpose.
ENVMAP_TO_WORLD = np.array([[0.0, 0.0, -1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
# Mitsuba's camera looks down local +z with +y up and +x to the left; OpenCV's has +x right, +y down.
OPENCV_TO_MITSUBA_CAMERA = np.diag([-1.0, -1.0, 1.0, 1.0])


_PROBE = """
import mitsuba as mi
mi.set_variant("{variant}")
scene = mi.load_dict({{"type": "scene", "integrator": {{"type": "path"}}, "s": {{"type": "sphere"}}, \
"e": {{"type": "constant"}},
    "sensor": {{"type": "perspective", "to_world": mi.ScalarTransform4f().translate([0, 0, -4]),
               "film": {{"type": "hdrfilm", "width": 4, "height": 4}}}}}})
mi.render(scene, spp=1)
"""
_RENDERS: dict[str, bool] = {}


def variant_renders(variant: str) -> bool:
    """Whether `variant` can render here, tried once per process in a child process: with an LLVM older
    than Dr.Jit needs (Debian 12's LLVM 15), llvm variants load but their first JIT compile aborts the
    whole process ("LLVM ERROR: Cannot select ..."), which no exception handler can catch."""
    if variant.startswith("scalar"):
        return True
    if variant not in _RENDERS:
        try:
            result = subprocess.run(
                [sys.executable, "-c", _PROBE.format(variant=variant)], capture_output=True, timeout=120
            )
            _RENDERS[variant] = result.returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            _RENDERS[variant] = False
    return _RENDERS[variant]


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


def select_variant(preferred: tuple[str, ...] | None = None) -> str:
    """Set the first Mitsuba variant of `preferred` that loads here and return its name (default: VARIANTS, after
    GPU_VARIANT where a CUDA GPU is; a variant that cannot render here is passed over)."""
    try:
        import mitsuba as mi
    except ImportError:
        raise ConfigError(
            "Mitsuba 3 is not installed; `matspray synth` needs it: pip install 'matspray[synth]'"
        ) from None
    current = mi.variant()
    if preferred is None:
        preferred = ((GPU_VARIANT,) if _cuda_available() else ()) + VARIANTS
    for variant in preferred:
        if not variant_renders(variant):
            continue  # e.g. llvm_ad_rgb with an LLVM < 16: install libllvm19 for the fast variant
        if current == variant:
            return variant
        try:
            mi.set_variant(variant)
            return variant
        except (ImportError, AttributeError, RuntimeError):
            continue
    raise ConfigError(
        f"none of the Mitsuba variants {', '.join(preferred)} loads on this machine (available: {mi.variants()})"
    )


def is_vectorised() -> bool:
    """True when the active variant traces many rays per call (llvm / cuda), False for scalar."""
    import mitsuba as mi

    return not mi.variant().startswith("scalar")


# ------------------------------------------------------------------------------------------ scene parts
def mesh_of(part: Part, bsdf: dict):
    """A Mitsuba mesh with the part's vertices, faces, vertex normals, texture coordinates and `bsdf`."""
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(
        part.name, len(part.vertices), len(part.faces), props=props, has_vertex_normals=True, has_vertex_texcoords=True
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = part.vertices.astype(np.float32).reshape(-1)
    params["faces"] = part.faces.astype(np.uint32).reshape(-1)
    params["vertex_normals"] = part.normals.astype(np.float32).reshape(-1)
    params["vertex_texcoords"] = part.uvs.astype(np.float32).reshape(-1)
    params.update()
    return mesh


def bitmap_texture(values: np.ndarray, sampling: Sampling = Sampling(), uvs: np.ndarray | None = None) -> dict:
    """A bilinear bitmap texture holding `values` [T, W] or [T, W, 3] as they are (linear), read through
    `sampling` (its UV transform and wrap modes; two different modes need the mesh's `uvs` [V, 2])."""
    import mitsuba as mi

    if sampling.wrap_s != sampling.wrap_t:
        if uvs is None:
            raise ConfigError("a texture with two wrap modes needs the mesh's UVs")
        values, sampling = single_wrap(values, sampling, uvs)
    array = np.ascontiguousarray(values, dtype=np.float32)
    if array.ndim == 2:
        array = array[..., None]
    texture = {
        "type": "bitmap",
        "bitmap": mi.Bitmap(array),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": sampling.wrap_s,
    }
    if sampling.to_uv is not None:
        to_uv = np.eye(4)
        to_uv[:2, :2], to_uv[:2, 3] = sampling.to_uv[:2, :2], sampling.to_uv[:2, 2]
        texture["to_uv"] = mi.ScalarTransform4f(to_uv.tolist())
    return texture


def principled_bsdf(textures: Textures, uvs: np.ndarray | None = None) -> dict:
    """Mitsuba's principled BSDF: textured base colour, roughness (GGX alpha = r^2) and metallic;
    specular 0.5 (F0 = 0.04 for dielectrics), no sheen, clearcoat or transmission; wrapped in Mitsuba's
    `twosided` for double-sided materials (else the back of a face is black)."""
    bsdf = {
        "type": "principled",
        "base_color": bitmap_texture(textures.base_color, textures.base_color_sampling, uvs),
        "roughness": bitmap_texture(textures.roughness, textures.metallic_roughness_sampling, uvs),
        "metallic": bitmap_texture(textures.metallic, textures.metallic_roughness_sampling, uvs),
        "specular": 0.5,
    }
    return {"type": "twosided", "bsdf": bsdf} if textures.double_sided else bsdf


def mitsuba_envmap_rows(env: np.ndarray) -> np.ndarray:  # [H, W, 3] -> [2H + 1, W, 3]
    """Our map resampled for Mitsuba's envmap, whose rows sit at v = i / (rows - 1) (the first and last on
    the poles) where ours sit at pixel centres v = (i + 0.5) / H.

    Rows at v = k / 2H interleave our pixel centres (odd k) with the midpoints between them (even k);
    our lookup is linear between centres and constant beyond the outer ones, so Mitsuba's linear
    interpolation between these rows reproduces it exactly.
    """
    height = env.shape[0]
    rows = np.empty((2 * height + 1,) + env.shape[1:], dtype=env.dtype)
    rows[1::2] = env
    rows[2:-1:2] = 0.5 * (env[:-1] + env[1:])
    rows[0], rows[-1] = env[0], env[-1]
    return rows


def envmap_emitter(env: np.ndarray) -> dict:
    """Environment emitter for a lat-long map [H, 2H, 3] (linear RGB) in matspray's convention."""
    import mitsuba as mi

    rows = np.ascontiguousarray(mitsuba_envmap_rows(np.asarray(env, dtype=np.float32)))
    bitmap = mi.Bitmap(rows, pixel_format=mi.Bitmap.PixelFormat.RGB)
    return {"type": "envmap", "bitmap": bitmap, "to_world": mi.ScalarTransform4f(ENVMAP_TO_WORLD.tolist())}


def camera_to_world(camera: Camera) -> np.ndarray:  # [4, 4] Mitsuba sensor to_world
    c2w = np.linalg.inv(camera.viewmat.double().cpu().numpy())  # OpenCV camera -> world
    return c2w @ OPENCV_TO_MITSUBA_CAMERA


def sampler_for(spp: int) -> str:
    """Mitsuba sampler for `spp` samples per pixel: "stratified" (a jittered s x s grid) when spp is a square,
    else "independent" (stratified would round the count). At the same cost stratified noise is well
    below independent's (docs/defaults.md), which matters when the renders are ground truth."""
    return "stratified" if math.isqrt(spp) ** 2 == spp else "independent"


def perspective_sensor(camera: Camera, spp: int) -> dict:
    """A pinhole sensor matching `camera` (centred principal point, square pixels), box-filtered RGBA film.

    The sampler is `sampler_for(spp)`."""
    import mitsuba as mi

    K = camera.K.double()
    if (
        abs(float(K[0, 0]) - float(K[1, 1])) > 1e-4 * float(K[0, 0])
        or abs(float(K[0, 2]) - camera.width / 2) > 1e-6
        or abs(float(K[1, 2]) - camera.height / 2) > 1e-6
    ):
        raise ConfigError("Mitsuba sensors here need square pixels and a centred principal point")
    return {
        "type": "perspective",
        "fov": math.degrees(camera.fov_x),
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": mi.ScalarTransform4f(camera_to_world(camera).tolist()),
        "sampler": {"type": sampler_for(spp), "sample_count": spp},
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "pixel_format": "rgba",
            "rfilter": {"type": "box"},
        },
    }


@dataclass(frozen=True)
class GroundPlane:
    """A square, one-sided ground plane facing +z at height `z`, `half_size` wide each way."""

    z: float
    half_size: float
    texture: np.ndarray | None = field(default=None, compare=False)  # [T, T, 3] linear base colour (a table)

    def shape(self) -> dict:
        import mitsuba as mi

        to_world = mi.ScalarTransform4f().translate([0.0, 0.0, self.z]) @ mi.ScalarTransform4f().scale(
            [self.half_size, self.half_size, 1.0]
        )
        plain = {"type": "rgb", "value": [GROUND_BASE_COLOR] * 3}
        bsdf = {
            "type": "principled",
            "base_color": plain if self.texture is None else bitmap_texture(self.texture),
            "roughness": GROUND_ROUGHNESS,
            "metallic": 0.0,
            "specular": 0.5,
        }
        return {"type": "rectangle", "to_world": to_world, "bsdf": bsdf}


def build_scene(
    parts: list[Part],
    textures: list[Textures],
    env: np.ndarray,
    show_env: bool = False,
    ground: GroundPlane | None = None,
):
    """The object (one mesh and principled BSDF per part) under environment `env` [H, 2H, 3], path traced.
    By default the emitter is hidden, so the film's alpha is the object's coverage; `show_env` puts the
    light behind the object and `ground` adds a ground plane, as in a real photo (alpha is then 1)."""
    import mitsuba as mi

    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH, "hide_emitters": not show_env},
        "light": envmap_emitter(env),
    }
    for index, (part, texture) in enumerate(zip(parts, textures)):
        scene[f"part_{index}"] = mesh_of(part, principled_bsdf(texture, part.uvs))
    if ground is not None:
        scene["ground"] = ground.shape()
    return mi.load_dict(scene)


def render_view(scene, camera: Camera, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Path trace one view -> straight (not premultiplied) linear rgb [H, W, 3] and alpha [H, W]."""
    import mitsuba as mi

    sensor = mi.load_dict(perspective_sensor(camera, spp))
    rgba = np.array(mi.render(scene, sensor=sensor, seed=seed, spp=spp), dtype=np.float64)  # [H, W, 4] premultiplied
    alpha = np.clip(rgba[..., 3], 0.0, 1.0)
    rgb = np.where(alpha[..., None] > 1e-6, rgba[..., :3] / np.maximum(alpha, 1e-6)[..., None], 0.0)
    return rgb.astype(np.float32), alpha.astype(np.float32)


# ------------------------------------------------------------------------------------------ ray casts
@dataclass
class Hits:
    """First surface hit of each ray (arrays over rays R; entries of missed rays are 0)."""

    valid: np.ndarray  # [R] bool
    distance: np.ndarray  # [R] ray parameter t (unit directions: distance)
    normal: np.ndarray  # [R, 3] shading normal (interpolated vertex normal), world space
    uv: np.ndarray  # [R, 2] texture coordinates
    part: np.ndarray  # [R] int, index of the part hit (-1 on a miss)


def part_index(scene) -> dict[str, int]:
    """Mitsuba shape id ('part_3') -> part index."""
    return {shape.id(): int(shape.id().split("_")[1]) for shape in scene.shapes()}


def intersect(scene, origins: np.ndarray, directions: np.ndarray) -> Hits:
    """Trace rays origins [R, 3], unit directions [R, 3] against `scene` (the geometry Mitsuba renders)."""
    if not is_vectorised():
        return intersect_one_by_one(scene, origins, directions)
    import mitsuba as mi

    o, d = origins.astype(np.float32), directions.astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    part = np.full(len(o), -1, dtype=np.int64)
    for shape in scene.shapes():
        part[np.array(si.shape == mi.ShapePtr(shape), dtype=bool) & valid] = part_index(scene)[shape.id()]
    normal = np.array(si.sh_frame.n, dtype=np.float64).reshape(3, -1).T
    uv = np.array(si.uv, dtype=np.float64).reshape(2, -1).T
    distance = np.array(si.t, dtype=np.float64)
    return Hits(valid, np.where(valid, distance, 0.0), normal * valid[:, None], uv * valid[:, None], part)


def intersect_one_by_one(scene, origins: np.ndarray, directions: np.ndarray) -> Hits:
    """The scalar variants trace one ray per call (slow; used only when no vectorised variant loads)."""
    import mitsuba as mi

    ids = part_index(scene)
    count = len(origins)
    hits = Hits(np.zeros(count, bool), np.zeros(count), np.zeros((count, 3)), np.zeros((count, 2)), np.full(count, -1))
    for r in range(count):
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*origins[r]), mi.Vector3f(*directions[r])))
        if not si.is_valid():
            continue
        hits.valid[r] = True
        hits.distance[r] = si.t
        hits.normal[r] = np.array(si.sh_frame.n)
        hits.uv[r] = np.array(si.uv)
        hits.part[r] = ids[si.shape.id()]
    return hits
