"""UV-mapped triangle meshes made in code, every one a parametric surface p(u, v).

A part is a closed surface sampled on a regular (u, v) grid: u runs around the part (periodic), v
from its top (v = 0) to its bottom (v = 1; periodic too for a torus). The grid's vertices carry the
(u, v) at which they were sampled, so a texture baked by evaluating p at texel centres lines up with
the mesh. Vertex normals are area-weighted face normals, averaged over vertices that share a
position (seams and poles), so shading is smooth everywhere.

Objects are centred at the origin with world up +z and fit in [-1, 1]^3.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from matspray.errors import ConfigError
from matspray.synth.noise import ValueNoise, fbm, rotation_about

# A surface maps texture coordinates u, v [...] (both in [0, 1]) to points [..., 3].
Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]

GRID_U, GRID_V = 192, 96  # vertices around and along each part


@dataclass
class Part:
    """One closed surface of an object and the mesh sampled from it."""

    name: str
    surface: Surface  # p(u, v) in world space
    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64, counter-clockwise seen from outside
    uvs: np.ndarray  # [V, 2] (u, v)
    normals: np.ndarray  # [V, 3] unit
    params: dict  # what made it (for scene.json)


# ------------------------------------------------------------------------------------------ surfaces
def unit_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # [...], [...] -> [..., 3]
    """Directions on the unit sphere: v = 0 at +z, v = 1 at -z, u the azimuth from +x."""
    theta, phi = np.pi * v, 2.0 * np.pi * u
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


def sphere_surface(radius: float) -> Surface:
    return lambda u, v: radius * unit_directions(u, v)


def rounded_cube_surface(half_size: float, exponent: float) -> Surface:
    """Superellipsoid |x|^n + |y|^n + |z|^n = s^n, reached by scaling each sphere direction radially."""

    def surface(u, v):
        d = unit_directions(u, v)
        norm = (np.abs(d) ** exponent).sum(-1) ** (1.0 / exponent)  # >= 3^(1/n - 1/2) > 0
        return half_size * d / norm[..., None]

    return surface


def torus_surface(major: float, minor: float) -> Surface:
    """Ring around z: u the angle around the ring, v the angle around the tube (v = 0 on the top)."""

    def surface(u, v):
        phi, psi = 2.0 * np.pi * u, 2.0 * np.pi * v
        ring = major + minor * np.sin(psi)
        return np.stack([ring * np.cos(phi), ring * np.sin(phi), minor * np.cos(psi)], axis=-1)

    return surface


def capsule_surface(radius: float, half_length: float) -> Surface:
    """Cylinder along z with hemispherical caps; v is arc length along the profile, top to bottom."""
    cap = 0.5 * np.pi * radius
    total = 2.0 * cap + 2.0 * half_length

    def surface(u, v):
        s = v * total  # arc length from the top pole
        angle = np.clip(s / radius, 0.0, 0.5 * np.pi)  # top cap: 0 (pole) .. pi/2 (equator)
        low = np.clip((s - cap - 2.0 * half_length) / radius, 0.0, 0.5 * np.pi)  # bottom cap
        rho = np.where(
            s < cap, radius * np.sin(angle), np.where(s > cap + 2 * half_length, radius * np.cos(low), radius)
        )
        z = np.where(
            s < cap,
            half_length + radius * np.cos(angle),
            np.where(s > cap + 2 * half_length, -half_length - radius * np.sin(low), half_length - (s - cap)),
        )
        phi = 2.0 * np.pi * u
        return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=-1)

    return surface


def blob_surface(radius: float, amplitude: float, frequency: float, noise: ValueNoise) -> Surface:
    """A sphere pushed in and out along its normal by smooth fractal noise of the direction."""

    def surface(u, v):
        d = unit_directions(u, v)
        return radius * (1.0 + amplitude * fbm(noise, d, frequency, octaves=3))[..., None] * d

    return surface


def placed(surface: Surface, rotation: np.ndarray, translation, scale: float = 1.0) -> Surface:
    """`surface` scaled, then rotated by rotation [3, 3], then moved by translation [3]."""
    offset = np.asarray(translation, dtype=np.float64)
    return lambda u, v: scale * surface(u, v) @ rotation.T + offset


# ------------------------------------------------------------------------------------------ meshing
def grid_mesh(surface: Surface, grid_u: int = GRID_U, grid_v: int = GRID_V) -> tuple[np.ndarray, ...]:
    """Sample `surface` on a (grid_v + 1) x (grid_u + 1) vertex grid.

    Returns vertices [V, 3], faces [F, 3] (outward winding), uvs [V, 2], normals [V, 3]. The seam
    column u = 1 duplicates u = 0 with its own texture coordinate, as UV-mapped meshes do.
    """
    u = np.linspace(0.0, 1.0, grid_u + 1)
    v = np.linspace(0.0, 1.0, grid_v + 1)
    uu, vv = np.meshgrid(u, v, indexing="xy")  # [grid_v + 1, grid_u + 1]
    vertices = surface(uu, vv).reshape(-1, 3)
    uvs = np.stack([uu, vv], axis=-1).reshape(-1, 2)
    row = grid_u + 1
    i, j = np.meshgrid(np.arange(grid_v), np.arange(grid_u), indexing="ij")
    a = (i * row + j).reshape(-1)  # (v, u)
    b, c, d = a + 1, a + row + 1, a + row  # (v, u+1), (v+1, u+1), (v+1, u)
    # u turns counter-clockwise around +z and v runs downwards, so (a, d, c) faces outwards
    faces = np.concatenate([np.stack([a, d, c], -1), np.stack([a, c, b], -1)])
    faces = drop_degenerate(vertices, faces)
    return vertices, faces, uvs, vertex_normals(vertices, faces)


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:  # [F, 3] -> [F', 3]
    """Remove zero-area triangles (the collapsed rows at a pole)."""
    p = vertices[faces]  # [F, 3, 3]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=-1)
    return faces[area2 > 1e-12 * max(1.0, float(area2.max()))]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:  # [V, 3], [F, 3] -> [V, 3]
    """Area-weighted face normals summed per position, so seam and pole copies get one normal."""
    p = vertices[faces]
    face_normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # [F, 3], length = 2 * area
    _, position_id = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    position_id = position_id.reshape(-1)
    sums = np.zeros((position_id.max() + 1, 3))
    for corner in range(3):
        np.add.at(sums, position_id[faces[:, corner]], face_normals)
    normals = sums[position_id]
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True).clip(1e-12)


def make_part(name: str, surface: Surface, params: dict, grid_u: int = GRID_U, grid_v: int = GRID_V) -> Part:
    vertices, faces, uvs, normals = grid_mesh(surface, grid_u, grid_v)
    return Part(name, surface, vertices, faces, uvs, normals, params)


# ------------------------------------------------------------------------------------------ shapes
def tilt(rng: np.random.Generator, max_degrees: float) -> np.ndarray:  # [3, 3]
    """A seeded rotation: spin about z, then lean by up to `max_degrees` about a horizontal axis."""
    spin = rotation_about([0.0, 0.0, 1.0], rng.uniform(0.0, 2.0 * np.pi))
    axis = np.array([np.cos(a := rng.uniform(0.0, 2.0 * np.pi)), np.sin(a), 0.0])
    return rotation_about(axis, np.radians(rng.uniform(0.0, max_degrees))) @ spin


def sphere(rng: np.random.Generator) -> list[Part]:
    rotation = tilt(rng, 30.0)  # turns the texture seam and poles away from the default cameras
    return [
        make_part(
            "sphere", placed(sphere_surface(0.9), rotation, [0, 0, 0]), {"radius": 0.9, "rotation": rotation.tolist()}
        )
    ]


def rounded_cube(rng: np.random.Generator) -> list[Part]:
    exponent = float(rng.uniform(6.0, 10.0))
    rotation = tilt(rng, 25.0)
    surface = placed(rounded_cube_surface(0.62, exponent), rotation, [0, 0, 0])
    return [
        make_part("rounded-cube", surface, {"half_size": 0.62, "exponent": exponent, "rotation": rotation.tolist()})
    ]


def torus(rng: np.random.Generator) -> list[Part]:
    minor = float(rng.uniform(0.22, 0.32))
    major = 0.92 - minor
    rotation = tilt(rng, 50.0)
    surface = placed(torus_surface(major, minor), rotation, [0, 0, 0])
    return [
        make_part(
            "torus", surface, {"major": major, "minor": minor, "rotation": rotation.tolist()}, GRID_U, GRID_U // 2
        )
    ]


def capsule(rng: np.random.Generator) -> list[Part]:
    radius = float(rng.uniform(0.35, 0.45))
    half_length = 0.9 - radius
    rotation = tilt(rng, 70.0)
    surface = placed(capsule_surface(radius, half_length), rotation, [0, 0, 0])
    return [
        make_part("capsule", surface, {"radius": radius, "half_length": half_length, "rotation": rotation.tolist()})
    ]


def blob(rng: np.random.Generator) -> list[Part]:
    amplitude, frequency = float(rng.uniform(0.15, 0.3)), float(rng.uniform(1.2, 2.2))
    surface = blob_surface(0.72, amplitude, frequency, ValueNoise(rng))
    return [make_part("blob", surface, {"radius": 0.72, "amplitude": amplitude, "frequency": frequency})]


def composite(rng: np.random.Generator) -> list[Part]:
    """A pedestal block, a ball resting on it, a leaning ring through both and a rod lying at the
    block's foot: the parts cast shadows on, reflect and hide each other."""
    spin = rotation_about([0.0, 0.0, 1.0], rng.uniform(0.0, 2.0 * np.pi))
    ring_lean = rotation_about([1.0, 0.0, 0.0], np.radians(rng.uniform(55.0, 75.0)))
    lying = rotation_about([0.0, 1.0, 0.0], np.pi / 2)
    layout = [
        ("block", rounded_cube_surface(1.0, 8.0), np.eye(3), [0.0, 0.0, -0.62], 0.38),
        ("ball", sphere_surface(1.0), tilt(rng, 30.0), [0.05, 0.0, 0.14], 0.4),
        ("ring", torus_surface(0.75, 0.18), ring_lean, [0.0, 0.0, 0.05], 0.8),
        ("rod", capsule_surface(0.3, 0.7), lying, [0.05, 0.46, -0.93], 0.22),
    ]
    parts = []
    for name, surface, rotation, offset, scale in layout:
        rotation = spin @ rotation
        offset = spin @ np.asarray(offset)
        params = {"rotation": rotation.tolist(), "translation": offset.tolist(), "scale": scale}
        grid_v = GRID_U // 2 if name == "ring" else GRID_V
        parts.append(make_part(f"composite/{name}", placed(surface, rotation, offset, scale), params, GRID_U, grid_v))
    return parts


SHAPES: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "sphere": sphere,
    "rounded-cube": rounded_cube,
    "torus": torus,
    "capsule": capsule,
    "blob": blob,
    "composite": composite,
}


def resolve_shape(name: str, seed: int) -> str:
    """`name`, or for 'random' the shape the seed picks; ConfigError listing the valid names otherwise."""
    if name == "random":
        return sorted(SHAPES)[np.random.default_rng([seed, 1]).integers(len(SHAPES))]
    if name not in SHAPES:
        raise ConfigError(f"unknown shape '{name}' (valid: {', '.join(SHAPES)}, random)")
    return name


def make_shape(name: str, rng: np.random.Generator) -> list[Part]:
    """The parts of shape `name` (see SHAPES), varied by `rng`."""
    if name not in SHAPES:
        raise ConfigError(f"unknown shape '{name}' (valid: {', '.join(SHAPES)}, random)")
    return SHAPES[name](rng)
