"""The turntable orbit of `matspray relight --views orbit` circles the object about the capture's own up axis,
whatever frame structure from motion put the poses in (issue 39)."""

import math

import pytest
import torch

from matspray.data.camera import Camera
from matspray.relight import cameras_up, orbit_cameras


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
    assert float(torch.nn.functional.normalize(first, dim=0) @ torch.nn.functional.normalize(reference[0].center.double() - target, dim=0)) > 0.999
    # consecutive frames are one step of the circle apart
    step = orbit[1].center.double() - orbit[0].center.double()
    assert float(step.norm()) == pytest.approx(2 * 3.0 * math.cos(0.4) * math.sin(math.pi / 12), rel=1e-6)
