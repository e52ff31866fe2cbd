"""Pinhole camera in the OpenCV convention (x right, y down, z forward).

`viewmat` maps world to camera coordinates; `K` holds the intrinsics with pixel centres at +0.5,
so the centre of pixel (column i, row j) is the continuous coordinate (i + 0.5, j + 0.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

# Blender / NeRF-synthetic cameras look down -z with y up (OpenGL); OpenCV looks down +z with y down.
OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass
class Camera:
    K: Tensor  # [3, 3] pinhole intrinsics
    viewmat: Tensor  # [4, 4] world-to-camera, OpenCV axes
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3) or tuple(self.viewmat.shape) != (4, 4):
            raise ValueError(
                f"Camera needs K [3, 3] and viewmat [4, 4], got {tuple(self.K.shape)} and {tuple(self.viewmat.shape)}"
            )
        self.width, self.height = int(self.width), int(self.height)

    # ---------------------------------------------------------------- construction
    @staticmethod
    def from_camtoworld_opengl(c2w: Tensor, K: Tensor, width: int, height: int) -> "Camera":
        """Camera from a Blender/NeRF camera-to-world matrix [4, 4] (OpenGL axes)."""
        c2w = torch.as_tensor(c2w, dtype=torch.float64, device=_device_of(c2w))
        c2w_cv = c2w @ OPENGL_TO_OPENCV.to(c2w.device)
        viewmat = torch.linalg.inv(c2w_cv)
        return Camera(
            K=torch.as_tensor(K, dtype=torch.float32, device=c2w.device),
            viewmat=viewmat.float(),
            width=width,
            height=height,
        )

    @staticmethod
    def from_fov_x(fov_x: float, width: int, height: int, viewmat: Tensor) -> "Camera":
        """Camera with square pixels, horizontal field of view `fov_x` (radians), centred principal point."""
        viewmat = torch.as_tensor(viewmat, device=_device_of(viewmat)).float()
        return Camera(
            K=intrinsics_from_fov(fov_x, width, height, viewmat.device), viewmat=viewmat, width=width, height=height
        )

    @staticmethod
    def look_at(eye, target, up, fov_x: float, width: int, height: int) -> "Camera":
        """Camera at `eye` looking at `target`; `up` is the world direction that appears up in the image. It is made
        on the device of whichever of them is a tensor (the CPU when none is)."""
        device = next((v.device for v in (eye, target, up) if isinstance(v, Tensor)), torch.device("cpu"))
        eye, target, up = (torch.as_tensor(v, dtype=torch.float64, device=device) for v in (eye, target, up))
        forward = target - eye
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, up)
        if right.norm() < 1e-9:  # looking along `up`: any perpendicular will do
            right = torch.linalg.cross(forward, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64, device=device))
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        c2w = torch.eye(4, dtype=torch.float64, device=device)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
        return Camera.from_fov_x(fov_x, width, height, torch.linalg.inv(c2w))

    # ---------------------------------------------------------------- properties
    def _cached(self, name: str, compute):
        """`compute()` once per pose and intrinsics: training reads the camera's derived matrices several times a
        step, and on a GPU each recomputation is a handful of kernel launches. Keyed on the tensors and their
        versions, so that a K or viewmat replaced or changed in place is computed again."""
        key = (id(self.K), self.K._version, id(self.viewmat), self.viewmat._version, self.viewmat.device)
        cached = self.__dict__.get(name)
        if cached is None or cached[0] != key:
            # the tensors are held with the value, so that their ids cannot be reused by others while it is kept
            self.__dict__[name] = cached = (key, compute(), self.K, self.viewmat)
        return cached[1]

    @property
    def camtoworld(self) -> Tensor:  # [4, 4] OpenCV axes
        return self._cached("_camtoworld", lambda: torch.linalg.inv(self.viewmat.double()).to(self.viewmat.dtype))

    def pixel_directions(self) -> Tensor:  # [H, W, 3] world space, scaled to camera z = 1
        """The world-space direction through each pixel centre, scaled so that a point at camera depth z along it
        is `center + z * direction` (computed once per camera)."""

        def directions() -> Tensor:
            K = self.K
            rows, cols = torch.meshgrid(
                torch.arange(self.height, device=K.device, dtype=K.dtype),
                torch.arange(self.width, device=K.device, dtype=K.dtype),
                indexing="ij",
            )
            x, y = (cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1]
            camera = torch.stack([x, y, torch.ones_like(x)], dim=-1)  # [H, W, 3]
            return camera @ self.camtoworld[:3, :3].to(camera).T

        return self._cached("_pixel_directions", directions)

    @property
    def camtoworld_opengl(self) -> Tensor:  # [4, 4] Blender/NeRF axes, float64 so that writers lose nothing
        return torch.linalg.inv(self.viewmat.double()) @ OPENGL_TO_OPENCV.to(self.viewmat.device)

    @property
    def center(self) -> Tensor:  # [3] camera position in world space
        return self.camtoworld[:3, 3]

    @property
    def fov_x(self) -> float:
        return 2.0 * math.atan(0.5 * self.width / float(self.K[0, 0]))

    @property
    def device(self) -> torch.device:
        return self.viewmat.device

    def to(self, device) -> "Camera":
        return Camera(self.K.to(device), self.viewmat.to(device), self.width, self.height)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 halves width and height)."""
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for its image resampled to `width` x `height` pixels (each axis by its own factor)."""
        K = self.K.clone()
        K[0] *= width / self.width
        K[1] *= height / self.height
        return Camera(K, self.viewmat.clone(), width, height)

    def cropped(self, left: int, top: int, width: int, height: int) -> "Camera":
        """The same camera for the `width` x `height` window of its image whose top-left pixel is (`left`, `top`):
        only the principal point moves."""
        K = self.K.clone()
        K[0, 2] -= left
        K[1, 2] -= top
        return Camera(K, self.viewmat.clone(), width, height)

    # ---------------------------------------------------------------- geometry
    def world_to_camera(self, points: Tensor) -> Tensor:  # [N, 3] -> [N, 3]
        R, t = self.viewmat[:3, :3].to(points), self.viewmat[:3, 3].to(points)
        return points @ R.T + t

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] -> continuous pixel coordinates [N, 2] and camera depth z [N]."""
        cam = self.world_to_camera(points)
        z = cam[:, 2]
        K = self.K.to(points)
        uv = cam[:, :2] / z.clamp_min(1e-12)[:, None]
        pixels = uv * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])
        return pixels, z

    def in_image(self, pixels: Tensor, z: Tensor) -> Tensor:  # [N, 2], [N] (`project`) -> [N] bool
        """Projected points in front of the camera whose pixel coordinates lie inside the image."""
        return (z > 1e-6) & (pixels >= 0).all(-1) & (pixels[:, 0] < self.width) & (pixels[:, 1] < self.height)

    def rays(self, samples_per_side: int = 1) -> tuple[Tensor, Tensor]:
        """Ray origins and unit directions in world space.

        Returns origins [H * W * s * s, 3] and directions [H * W * s * s, 3], ordered by pixel (row-major)
        and then by sub-pixel sample on an s x s grid (sample centres at (k + 0.5) / s inside the pixel).
        """
        pixels = pixel_sample_grid(self.height, self.width, samples_per_side, device=self.device)  # [P, 2]
        return self.rays_through(pixels)

    def rays_through(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """Rays through continuous pixel coordinates [P, 2] -> origins [P, 3], unit directions [P, 3]."""
        K = self.K.to(pixels)
        x = (pixels[:, 0] - K[0, 2]) / K[0, 0]
        y = (pixels[:, 1] - K[1, 2]) / K[1, 1]
        dirs_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        c2w = self.camtoworld.to(pixels)
        dirs = dirs_cam @ c2w[:3, :3].T
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        origins = c2w[:3, 3].expand_as(dirs)
        return origins, dirs


def intrinsics_from_fov(fov_x: float, width: int, height: int, device="cpu") -> Tensor:  # [3, 3]
    focal = 0.5 * width / math.tan(0.5 * fov_x)
    return torch.tensor(
        [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float32, device=device
    )


def rigid_problem(c2w: Tensor, tolerance: float = 1e-3) -> str | None:
    """Why a [4, 4] camera-to-world matrix is not a rotation plus a translation, or None when it is one.

    A camera pose has no scale, shear or mirror: a scaled pose still renders, but every ray then comes out
    of the wrong place, so training runs on and learns nonsense. `tolerance` bounds |R^T R - I| and the
    last row's distance from (0, 0, 0, 1); poses rounded to float32 or to 6 decimals pass.
    """
    m = torch.as_tensor(c2w, device=_device_of(c2w)).double()
    if tuple(m.shape) != (4, 4):
        return f"it is {tuple(m.shape)}, not 4x4"
    if not torch.isfinite(m).all() or not torch.isfinite(m.float()).all():  # the cameras are float32
        return "it holds NaN, Inf or numbers too large for float32"
    last = m[3]
    if (last - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64, device=m.device)).abs().max() > tolerance:
        return f"its last row is ({', '.join(f'{v:.4g}' for v in last.tolist())}), not (0, 0, 0, 1)"
    R = m[:3, :3]
    lengths = R.norm(dim=0)
    if float(lengths.min()) < tolerance or abs(float(torch.linalg.det(R))) < tolerance:
        return "its rotation part is singular (zero or degenerate columns)"
    if (R.T @ R - torch.eye(3, dtype=torch.float64, device=m.device)).abs().max() > tolerance:
        return (
            "its rotation part is scaled or sheared (column lengths "
            f"{', '.join(f'{v:.4g}' for v in lengths.tolist())}, "
            "not orthonormal)"
        )
    if float(torch.linalg.det(R)) < 0:
        return "its rotation part is a mirror (determinant -1), not a rotation"
    return None


def _device_of(value) -> torch.device:  # a tensor's device; the CPU for arrays and lists (host data)
    return value.device if isinstance(value, Tensor) else torch.device("cpu")


def pixel_sample_grid(height: int, width: int, samples_per_side: int = 1, device=None) -> Tensor:
    """Continuous coordinates [H * W * s * s, 2] (x, y) of an s x s sample grid inside every pixel."""
    s = int(samples_per_side)
    offsets = (torch.arange(s, device=device, dtype=torch.float32) + 0.5) / s  # [s]
    oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
    sub = torch.stack([ox.reshape(-1), oy.reshape(-1)], dim=-1)  # [s*s, 2]
    rows, cols = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    corners = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=-1).float()  # [H*W, 2]
    return (corners[:, None, :] + sub[None, :, :]).reshape(-1, 2)
