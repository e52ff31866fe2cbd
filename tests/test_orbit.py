"""The turntable orbit of `matspray relight --views orbit` circles the object about the capture's own up axis,
whatever frame structure from motion put the poses in."""

import math

import numpy as np
import pytest
import torch

from matspray.data.camera import Camera
from matspray.method.relight import cameras_up, orbit_cameras
from matspray.synth.analytic import spiral_cameras
from matspray.synth.cameras import FOV_X, sphere_cameras


def ring(up, target, count=6, distance=3.0, elevation=0.4):
    """Cameras around `target` at one elevation above the plane normal to `up`, each holding `up` as image up."""
    up = torch.nn.functional.normalize(torch.tensor(up, dtype=torch.float64), dim=0)
    side = torch.linalg.svd(up[None]).Vh[1]
    other = torch.linalg.cross(up, side)
    target = torch.tensor(target, dtype=torch.float64)
    cameras = []
    for i in range(count):
        a = 2 * math.pi * i / count + 0.3
        direction = math.cos(elevation) * (math.cos(a) * side + math.sin(a) * other) + math.sin(elevation) * up
        cameras.append(Camera.look_at(target + distance * direction, target, up, 0.8, 32, 24))
    return cameras, up, target


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, -1.0, 0.0), (0.3, -0.8, 0.5)])
def test_orbit_keeps_distance_and_elevation_about_the_cameras_up(up):
    reference, axis, target = ring(up, (0.5, -0.2, 1.0))
    assert torch.allclose(cameras_up(reference), axis, atol=1e-9)
    orbit = orbit_cameras(reference, target, frames=12, up=cameras_up(reference))
    for camera in orbit:
        offset = camera.center.double() - target
        assert float(offset.norm()) == pytest.approx(3.0, abs=1e-6)
        assert float(torch.asin(offset @ axis / offset.norm())) == pytest.approx(0.4, abs=1e-6)
        assert float(-camera.camtoworld[:3, 1].double() @ axis) > 0.9  # the object stays upright in the frames
        assert torch.allclose(camera.K, reference[0].K)
    # the first frame looks from the side of the first reference camera
    first = orbit[0].center.double() - target
    assert (
        float(
            torch.nn.functional.normalize(first, dim=0)
            @ torch.nn.functional.normalize(reference[0].center.double() - target, dim=0)
        )
        > 0.999
    )
    # consecutive frames are one step of the circle apart
    step = orbit[1].center.double() - orbit[0].center.double()
    assert float(step.norm()) == pytest.approx(2 * 3.0 * math.cos(0.4) * math.sin(math.pi / 12), rel=1e-6)


def test_sphere_and_spiral_cameras_are_the_formulas_they_were_before_the_rename():
    """synth's cameras at given directions and the analytic object's Fibonacci spiral, against the formulas written
    out (they were both called orbit_cameras; renaming must not move a camera, since datasets are made with them)."""
    directions = np.array([[0.6, 0.0, 0.8], [0.0, -0.96, 0.28], [-0.36, 0.48, 0.8]])
    for camera, d in zip(sphere_cameras(directions, 2.5, 16), directions):
        expected = Camera.look_at((2.5 * d).tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], FOV_X, 16, 16)
        assert torch.equal(camera.viewmat, expected.viewmat) and torch.equal(camera.K, expected.K)
    golden = math.pi * (3 - math.sqrt(5))
    cameras = spiral_cameras(5, 12, phase=1.0)
    for i, camera in enumerate(cameras):
        elevation, azimuth = math.radians(-30 + 105 * (i + 0.5) / 5), i * golden + 1.0
        eye = [
            3.2 * math.cos(elevation) * math.cos(azimuth),
            3.2 * math.cos(elevation) * math.sin(azimuth),
            3.2 * math.sin(elevation),
        ]
        expected = Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40.0), 12, 12)
        assert torch.equal(camera.viewmat, expected.viewmat) and torch.equal(camera.K, expected.K)
