"""COLMAP sparse reconstructions (through pycolmap): `sparse/0` (or `sparse/`), `images/`, optional `masks/`.

Pinhole models are read as they are; distorted ones (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV,
OPENCV_FISHEYE and the radial fisheye models) are undistorted on load, masks the same way
(`matspray.data.undistort`). Every `test_every`-th image (sorted by name) is held out as a test view, as LLFF-style evaluations do.
"""

from __future__ import annotations

import math
from functools import partial
from pathlib import Path

import numpy as np
import torch

from matspray.data.camera import Camera
from matspray.data.images import read_image, srgb_to_linear
from matspray.data.scene import View
from matspray.data.undistort import Lens, Undistorter
from matspray.errors import DataError, file_error

# COLMAP camera models as a Lens: (focal x, focal y, cx, cy, distortion coefficients, fisheye), from the params
LENSES = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], (), False),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], (), False),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0), False),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0), False),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:8]), False),
    "FULL_OPENCV": lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:12]), False),
    "OPENCV_FISHEYE": lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:8]), True),
    "SIMPLE_RADIAL_FISHEYE": lambda p: (p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0), True),
    "RADIAL_FISHEYE": lambda p: (p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0), True),
}
MASK_SUFFIXES = (".png", ".jpg", ".jpeg")
MAX_SIZE = 1 << 16  # pixels on a side; more is a corrupt cameras file, not a photo


def find_model(root: Path) -> Path | None:
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if any((candidate / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            return candidate
    return None


def colmap_lens(camera, model_path: Path) -> Lens:
    """The Lens of a COLMAP camera; models without an OpenCV equivalent are refused, naming the known ones."""
    name = camera.model_name
    if name not in LENSES:
        raise file_error(model_path, f"camera {camera.camera_id} uses the camera model {name}, which MatSpray cannot undistort",
                         f"known: {', '.join(LENSES)}")
    params = [float(p) for p in camera.params]
    try:
        fx, fy, cx, cy, coeffs, fisheye = LENSES[name](params)
    except IndexError:
        raise file_error(model_path, f"camera {camera.camera_id} ({name}) has only {len(params)} parameters") from None
    # a zero, negative or NaN focal length still renders, so training would run on and learn nonsense; the
    # cameras are float32, where 1e-320 is 0 and 1e39 is Inf
    K = torch.tensor([fx, fy, cx, cy], dtype=torch.float32)
    sizes_ok = all(1 <= size <= MAX_SIZE for size in (camera.width, camera.height))  # a negative size reads as 2**64 - n
    if not all(math.isfinite(p) for p in params) or not (torch.isfinite(K).all() and K[0] > 0 and K[1] > 0) or not sizes_ok:
        raise file_error(model_path, f"camera {camera.camera_id} ({name}) has parameters {', '.join(f'{p:.4g}' for p in params)} "
                         f"for {camera.width}x{camera.height} px: focal lengths must be > 0 and every parameter finite",
                         "rerun COLMAP's mapper, or fix cameras.txt")
    return Lens(fx, fy, cx, cy, int(camera.width), int(camera.height), tuple(coeffs), fisheye, name)


def find_mask(mask_dir: Path, image_name: str) -> Path | None:
    for name in (image_name, Path(image_name).stem):
        for suffix in ("",) + MASK_SUFFIXES:
            candidate = mask_dir / (name + suffix)
            if candidate.is_file():
                return candidate
    return None


def read_colmap(root: Path, test_every: int = 8) -> tuple[list[View], list[View], torch.Tensor, torch.Tensor, list[str]]:
    """Returns train views, test views, points [P, 3], their linear colours [P, 3] and notes on what loading did."""
    import pycolmap

    model_path = find_model(root)
    if model_path is None:
        raise file_error(root, "no COLMAP model found", "expected sparse/0/cameras.bin or sparse/cameras.bin")
    try:
        reconstruction = pycolmap.Reconstruction(str(model_path))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError subclasses
        raise file_error(model_path, f"cannot read the COLMAP model: {exc}") from None
    images = sorted(reconstruction.images.values(), key=lambda image: image.name)
    images = [image for image in images if image.has_pose]
    if not images:
        raise file_error(model_path, "the COLMAP model has no registered images")
    image_dir = root / "images"
    mask_dir = root / "masks"
    views = []
    undistorter = Undistorter(root)
    for image in images:
        camera = reconstruction.cameras[image.camera_id]
        lens = colmap_lens(camera, model_path)
        cam_from_world = torch.tensor(image.cam_from_world().matrix(), dtype=torch.float64)  # [3, 4]
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3] = cam_from_world
        image_path = image_dir / image.name
        mask_path = None
        if mask_dir.is_dir():
            mask_path = find_mask(mask_dir, image.name)
            if mask_path is None:
                raise file_error(mask_dir, f"no mask for image '{image.name}'", "give every image a mask or remove masks/")
        load = partial(read_photo, image_path, mask_path, (camera.height, camera.width))
        sources = () if mask_path is None else (mask_path,)
        views.append(undistorter.view(Path(image.name).stem, image_path, lens, viewmat, load, sources))
    if test_every > 0 and len(views) > 1:
        test = [v for i, v in enumerate(views) if i % test_every == 0]
        train = [v for i, v in enumerate(views) if i % test_every != 0]
    else:
        train, test = views, []
    points3d = list(reconstruction.points3D.values())
    if points3d:
        points = torch.from_numpy(np.array([p.xyz for p in points3d], dtype=np.float32))
        colors = srgb_to_linear(torch.from_numpy(np.array([p.color for p in points3d], dtype=np.float32)) / 255.0)
    else:
        points = torch.zeros(0, 3)
        colors = torch.zeros(0, 3)
    if not train:
        raise DataError(f"{model_path}: too few images to hold out test views")
    return train, test, points, colors, undistorter.notes()


def read_photo(image_path: Path, mask_path: Path | None, size: tuple[int, int]):
    """rgb [H, W, 3] and alpha [H, W] (from the mask, or None) of one COLMAP image of `size` (H, W)."""
    rgb, alpha = read_image(image_path)
    if rgb.shape[:2] != size:
        raise file_error(image_path, f"image is {rgb.shape[1]}x{rgb.shape[0]} but its COLMAP camera is {size[1]}x{size[0]}")
    if mask_path is not None:
        mask_rgb, _ = read_image(mask_path)
        alpha = mask_rgb.mean(-1)
        if alpha.shape != rgb.shape[:2]:
            raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
    return rgb, alpha
