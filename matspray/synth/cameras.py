"""Cameras on a sphere around the object, looking at its centre (NeRF-synthetic style).

Training cameras follow a Fibonacci spiral over an elevation band (even coverage); test cameras are
seeded random positions on the same band, so the two sets are disjoint. The distance is chosen so
the object's bounding sphere fills most of the frame at the NeRF-synthetic field of view.
"""

from __future__ import annotations

import math

import numpy as np

from matspray.data.camera import Camera

FOV_X = 0.6911112070083618  # radians, NeRF-synthetic's camera_angle_x
FILL = 0.92  # the bounding sphere's angular radius as a fraction of half the field of view
MIN_ELEVATION, MAX_ELEVATION = -20.0, 70.0  # degrees; the poles are avoided (image up is world +z)
GROUND_MIN_ELEVATION = 10.0  # degrees; with a ground plane every camera stays above it
TURNTABLE_ELEVATION = 20.0  # degrees; the one ring of a turntable capture (a camera on a tripod beside the table)
FRONT_MAX_ELEVATION = 45.0  # degrees; a capture from one side: views up to this elevation
FRONT_HALF_AZIMUTH = 75.0  # degrees either side of the front (-y): the back of the object is never seen square on
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def framing_distance(bounding_radius: float, fov_x: float = FOV_X, fill: float = FILL) -> float:
    """Distance at which a sphere of `bounding_radius` spans `fill` of the field of view."""
    return bounding_radius / math.sin(0.5 * fov_x * fill)


def band_point(azimuth: np.ndarray, height: np.ndarray) -> np.ndarray:  # [N], [N] -> [N, 3] unit
    """Points on the unit sphere from azimuth (radians) and z = sin(elevation)."""
    ring = np.sqrt(1.0 - height**2)
    return np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), height], axis=-1)


def band_heights(min_elevation: float) -> tuple[float, float]:
    """z range of the elevation band from `min_elevation` (degrees) to MAX_ELEVATION."""
    return math.sin(math.radians(min_elevation)), math.sin(math.radians(MAX_ELEVATION))


def fibonacci_directions(
    count: int, phase: float, min_elevation: float = MIN_ELEVATION
) -> np.ndarray:  # [count, 3] unit
    """An even spiral over the elevation band, equal area per point, turned by `phase` radians."""
    low, high = band_heights(min_elevation)
    k = np.arange(count)
    height = high - (k + 0.5) / count * (high - low)
    return band_point(phase + GOLDEN_ANGLE * k, height)


def random_directions(
    count: int, rng: np.random.Generator, min_elevation: float = MIN_ELEVATION
) -> np.ndarray:  # [count, 3] unit
    """Uniform (equal area) random points on the elevation band."""
    low, high = band_heights(min_elevation)
    return band_point(rng.uniform(0.0, 2.0 * math.pi, count), rng.uniform(low, high, count))


def front_directions(
    count: int, rng: np.random.Generator, min_elevation: float, spiral: bool
) -> np.ndarray:  # [count, 3] unit
    """Directions over the front half of the band from `min_elevation` to FRONT_MAX_ELEVATION degrees (azimuths
    within FRONT_HALF_AZIMUTH of -y): an even golden-ratio spread (`spiral`) or uniform random ones."""
    low, high = math.sin(math.radians(min_elevation)), math.sin(math.radians(FRONT_MAX_ELEVATION))
    if spiral:
        k = np.arange(count)
        spread = (k * (math.sqrt(5.0) - 1.0) / 2.0 + rng.uniform()) % 1.0  # golden-ratio steps: even in azimuth
        height = high - (k + 0.5) / count * (high - low)
    else:
        spread, height = rng.uniform(0.0, 1.0, count), rng.uniform(low, high, count)
    half = math.radians(FRONT_HALF_AZIMUTH)
    return band_point(-0.5 * math.pi + half * (2.0 * spread - 1.0), height)


def ring_directions(azimuths: np.ndarray, elevation: float = TURNTABLE_ELEVATION) -> np.ndarray:  # [N] -> [N, 3]
    """Points on the ring at `elevation` degrees: the views of a turntable capture."""
    return band_point(azimuths, np.full_like(azimuths, math.sin(math.radians(elevation))))


def sphere_cameras(directions: np.ndarray, distance: float, resolution: int, fov_x: float = FOV_X) -> list[Camera]:
    """Square cameras at `distance` along each direction [N, 3], looking at the origin, world +z up."""
    return [
        Camera.look_at((distance * d).tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], fov_x, resolution, resolution)
        for d in directions
    ]


def make_cameras(
    train: int,
    test: int,
    bounding_radius: float,
    resolution: int,
    rng: np.random.Generator,
    min_elevation: float = MIN_ELEVATION,
    layout: str = "sphere",
    fill: float = FILL,
) -> tuple[list[Camera], list[Camera], float]:
    """Train and test cameras and the distance they sit at (the bounding sphere spans `fill` of the field of view).
    `layout` 'sphere': a spiral over the band from `min_elevation` degrees (test cameras random on it); 'turntable':
    evenly around the TURNTABLE_ELEVATION ring (test cameras at random azimuths on it); 'front': the front half of
    the band up to FRONT_MAX_ELEVATION (`front_directions`)."""
    distance = framing_distance(bounding_radius, fill=fill)
    phase = rng.uniform(0.0, 2.0 * math.pi)
    if layout == "front":
        train_directions = front_directions(train, rng, min_elevation, spiral=True)
        test_directions = front_directions(test, rng, min_elevation, spiral=False)
    elif layout == "turntable":
        train_directions = ring_directions(phase + 2.0 * math.pi * np.arange(train) / train)
        test_directions = ring_directions(rng.uniform(0.0, 2.0 * math.pi, test))
    else:
        train_directions = fibonacci_directions(train, phase, min_elevation)
        test_directions = random_directions(test, rng, min_elevation)
    return (
        sphere_cameras(train_directions, distance, resolution),
        sphere_cameras(test_directions, distance, resolution),
        distance,
    )
