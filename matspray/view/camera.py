"""Cameras between viser and MatSpray.

viser reports a browser's camera as the rotation R (quaternion wxyz) and position t of P_world = R p_camera + t, with
the camera frame in the OpenCV convention (x right, y down, z forward: looking along +Z, up is -Y), the vertical field
of view in radians and the canvas size in pixels. That is `matspray.data.camera`'s convention too, so the conversion is
an inversion of the pose plus a pinhole K with square pixels and a centred principal point; no axis flips.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from matspray.data.camera import Camera
from matspray.gaussians import quaternion_to_matrix


def matrix_to_quaternion(R) -> np.ndarray:  # [3, 3] rotation -> [4] (w, x, y, z), w >= 0
    """Shepperd's method: take the largest of the four squared components, so no branch divides by a small number."""
    R = np.asarray(R, dtype=np.float64)
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    candidates = [trace, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 1e-300))
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-300))
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-300))
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-300))
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def camera_from_viser(wxyz, position, fov_y: float, width: int, height: int) -> Camera:
    """The Camera that sees what viser's camera (pose, vertical field of view in radians) sees in a
    width x height image."""
    if width < 1 or height < 1 or not 0.0 < fov_y < math.pi:
        raise ValueError(f"viser camera: need a positive size and 0 < fov < pi, got {width} x {height}, fov {fov_y}")
    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64))  # any length > 0
    R = quaternion_to_matrix(q / q.norm()).numpy()
    t = np.asarray(position, dtype=np.float64)
    viewmat = np.eye(4)
    viewmat[:3, :3] = R.T  # world -> camera is the inverse of P_world = R p_camera + t
    viewmat[:3, 3] = -R.T @ t
    focal = 0.5 * height / math.tan(0.5 * fov_y)  # square pixels: the same focal length across
    K = torch.tensor([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(K, torch.from_numpy(viewmat).float(), width, height)


def viser_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz [4], position [3], vertical field of view) that make viser show `camera`'s view."""
    c2w = np.linalg.inv(camera.viewmat.detach().double().cpu().numpy())
    fov_y = 2.0 * math.atan(0.5 * camera.height / float(camera.K[1, 1]))
    return matrix_to_quaternion(c2w[:3, :3]), c2w[:3, 3].copy(), fov_y


def frame_size(aspect: float, long_side: int) -> tuple[int, int]:
    """(width, height) of an image with `long_side` pixels along its longer side and the canvas's aspect
    (width / height)."""
    if not aspect > 0 or long_side < 1:
        raise ValueError(f"frame_size: aspect {aspect} and long side {long_side} must be positive")
    if aspect >= 1.0:
        return long_side, max(1, round(long_side / aspect))
    return max(1, round(long_side * aspect)), long_side
