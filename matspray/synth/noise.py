"""Seeded 3D noise for shapes and materials: value noise, fractal sums of it, and Voronoi cells.

Pure numpy functions of world positions, so a pattern is continuous across UV seams and across the
parts of a composite object.
"""

from __future__ import annotations

import numpy as np

LATTICE = 64  # lattice values repeat every 64 units; objects span a few units at most frequencies used


class ValueNoise:
    """Smooth 3D value noise in [-1, 1]: random values on an integer lattice, blended with quintic fades."""

    def __init__(self, rng: np.random.Generator):
        self.values = rng.uniform(-1.0, 1.0, size=(LATTICE, LATTICE, LATTICE))  # [L, L, L]
        self.offset = rng.uniform(0.0, LATTICE, size=3)  # decorrelates noises made from one generator

    def __call__(self, points: np.ndarray) -> np.ndarray:  # [..., 3] -> [...]
        p = points + self.offset
        cell = np.floor(p)
        f = p - cell
        fade = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)  # [..., 3]
        i = cell.astype(np.int64) % LATTICE
        j = (i + 1) % LATTICE
        result = np.zeros(points.shape[:-1])
        for corner in range(8):
            pick = [(corner >> axis) & 1 for axis in range(3)]
            index = tuple(np.where(pick[axis], j[..., axis], i[..., axis]) for axis in range(3))
            weight = np.prod([fade[..., a] if pick[a] else 1.0 - fade[..., a] for a in range(3)], axis=0)
            result += weight * self.values[index]
        return result


def fbm(noise: ValueNoise, points: np.ndarray, frequency: float, octaves: int = 4, gain: float = 0.5) -> np.ndarray:
    """Fractal sum of `octaves` noise layers, doubling frequency and scaling amplitude by `gain`; [..., 3] -> [...].

    Normalised so the result stays in [-1, 1].
    """
    total = np.zeros(points.shape[:-1])
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        total += amplitude * noise(points * frequency * 2.0**octave + 17.0 * octave)
        norm += amplitude
        amplitude *= gain
    return total / norm


def voronoi(points: np.ndarray, sites: np.ndarray, chunk: int = 1 << 16) -> tuple[np.ndarray, np.ndarray]:
    """Nearest site per point and the gap to the second nearest.

    points: [N, 3], sites: [S, 3] (S >= 2) -> nearest index [N] int, second - first distance [N].
    The gap is 0 on a cell border and grows inside a cell, so thresholding it draws borders.
    """
    nearest = np.empty(len(points), dtype=np.int64)
    gap = np.empty(len(points))
    for start in range(0, len(points), chunk):
        block = points[start : start + chunk]
        dist = np.linalg.norm(block[:, None, :] - sites[None, :, :], axis=-1)  # [n, S]
        order = np.argpartition(dist, 1, axis=1)[:, :2]  # [n, 2] unordered two nearest
        two = np.take_along_axis(dist, order, axis=1)
        first = np.argmin(two, axis=1)
        nearest[start : start + chunk] = np.take_along_axis(order, first[:, None], axis=1)[:, 0]
        gap[start : start + chunk] = np.abs(two[:, 1] - two[:, 0])
    return nearest, gap


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:  # [3], radians -> [3, 3] (Rodrigues)
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
