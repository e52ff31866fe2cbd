"""Views and scenes: what every stage reads."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.images import resize

# a capture's own point cloud (structure from motion) with fewer points than this does not start the Gaussians: they
# start from triangulated points (data.triangulate) or at random (geometry.init)
MIN_COLMAP_POINTS = 100


@dataclass
class View:
    name: str  # unique within its split, e.g. "r_000"
    image: Tensor  # [H, W, 3] linear RGB, float32
    alpha: Tensor | None  # [H, W] in [0, 1], or None when the data has no mask
    camera: Camera
    path: Path | None = None  # the file the image came from

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def scaled(self, factor: float) -> "View":
        camera = self.camera.scaled(factor)
        return self.resized(camera.width, camera.height)

    def resized(self, width: int, height: int) -> "View":
        """The view resampled to `width` x `height` pixels (image, alpha and camera)."""
        image = resize(self.image, height, width)
        # a coverage stays in [0, 1]: the filter's rounding reaches 1 + 1e-7 inside, which masked metrics refuse
        alpha = None if self.alpha is None else resize(self.alpha, height, width).clamp(0.0, 1.0)
        return View(self.name, image, alpha, self.camera.resized(width, height), self.path)

    def cropped(self, left: int, top: int, width: int, height: int) -> "View":
        """The `width` x `height` window of the view whose top-left pixel is (`left`, `top`)."""
        if not (0 <= left and 0 <= top and left + width <= self.width and top + height <= self.height):
            size = f"{self.width}x{self.height}"
            raise ValueError(f"window {width}x{height} at ({left}, {top}) is not inside the {size} view '{self.name}'")
        rows, cols = slice(top, top + height), slice(left, left + width)
        alpha = None if self.alpha is None else self.alpha[rows, cols]
        return View(self.name, self.image[rows, cols], alpha, self.camera.cropped(left, top, width, height), self.path)

    def to(self, device) -> "View":
        alpha = None if self.alpha is None else self.alpha.to(device)
        return View(self.name, self.image.to(device), alpha, self.camera.to(device), self.path)


@dataclass
class Scene:
    train: list[View]
    test: list[View]
    bounds: Tensor  # [2, 3] axis-aligned box (min, max) around the object
    source: Path | None = None  # dataset folder
    format: str = ""  # reader that produced it: blender, tensoir, colmap
    points: Tensor | None = None  # [P, 3] sparse points (COLMAP), for initialisation
    point_colors: Tensor | None = None  # [P, 3] linear RGB
    notes: list[str] = field(default_factory=list)  # non-fatal observations made while loading
    log: list[str] = field(default_factory=list)  # what loading did to the data (undistortion, keys ignored)
    downscale: float = 1.0  # the factor the images were shrunk by on load

    @property
    def views(self) -> list[View]:
        return self.train + self.test

    @property
    def has_masks(self) -> bool:
        return all(v.alpha is not None for v in self.views)

    def split(self, name: str) -> list[View]:
        if name not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got '{name}'")
        return self.train if name == "train" else self.test


def bounds_from_visual_hull(views: list[View], resolution: int = 48, padding: float = 0.05) -> Tensor | None:
    """Axis-aligned box [2, 3] around the region every view's mask sees as object (visual hull).

    Starts from the box the cameras look into and keeps the voxels that project inside every mask.
    Returns None when views have no masks or the hull comes out empty.
    """
    masked = [v for v in views if v.alpha is not None]
    if len(masked) < 2:
        return None
    centers = torch.stack([v.camera.center.double() for v in masked])
    focus = focus_point(masked)
    radius = float((centers - focus).norm(dim=-1).max())
    lo, hi = focus - radius, focus + radius
    axis = torch.linspace(0.0, 1.0, resolution, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    points = (lo + grid * (hi - lo)).float()  # [R^3, 3]
    inside = torch.ones(points.shape[0], dtype=torch.bool)
    seen = torch.zeros(points.shape[0], dtype=torch.int32)
    for view in masked:
        pixels, depth = view.camera.project(points)
        cols, rows = pixels[:, 0].floor().long(), pixels[:, 1].floor().long()
        valid = (depth > 0) & (cols >= 0) & (rows >= 0) & (cols < view.width) & (rows < view.height)
        hit = torch.zeros_like(inside)
        hit[valid] = view.alpha[rows[valid], cols[valid]].cpu() > 0.5
        inside &= hit | ~valid  # a view constrains only the voxels inside its frame
        seen += valid.int()
    inside &= seen >= max(2, len(masked) // 2)  # and a voxel must be constrained by enough views
    if not inside.any():
        return None
    kept = points[inside]
    cell = (hi - lo).float() / (resolution - 1)
    box = torch.stack([kept.min(0).values - cell, kept.max(0).values + cell])
    pad = padding * (box[1] - box[0])
    return torch.stack([box[0] - pad, box[1] + pad])


def focus_point(views: list[View]) -> Tensor:
    """The point [3] closest (least squares) to every camera's optical axis: what the cameras look at."""
    return cameras_focus([v.camera for v in views])


def cameras_focus(cameras: list[Camera]) -> Tensor:  # -> [3] float64
    """The point closest (least squares) to every camera's optical axis."""
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for camera in cameras:
        c2w = camera.camtoworld.double().cpu()
        d = c2w[:3, 2] / c2w[:3, 2].norm()
        P = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
        A += P
        b += P @ c2w[:3, 3]
    return torch.linalg.lstsq(A, b).solution


def bounds_from_cameras(views: list[View]) -> Tensor:
    """Fallback box [2, 3]: centred on the focus point, half the nearest camera distance wide."""
    focus = focus_point(views)
    nearest = min(float((v.camera.center.double() - focus).norm()) for v in views)
    half = 0.5 * nearest
    return torch.stack([focus - half, focus + half]).float()


def bounds_from_points(points: Tensor, quantile: float = 0.02) -> Tensor:
    """Robust box [2, 3] around a point cloud [P, 3], ignoring the outer `quantile` on each side."""
    lo = torch.quantile(points.double(), quantile, dim=0)
    hi = torch.quantile(points.double(), 1.0 - quantile, dim=0)
    pad = 0.1 * (hi - lo)
    return torch.stack([lo - pad, hi + pad]).float()


def dataset_identity(scene: Scene) -> dict:
    """What a run folder records of the dataset it was made from, and its stages' fingerprints start from."""
    return {
        "source": str(Path(scene.source).resolve()) if scene.source else None,
        "format": scene.format,
        "train_views": [v.name for v in scene.train],
        "test_views": [v.name for v in scene.test],
        "resolution": [scene.train[0].width, scene.train[0].height],
    }
