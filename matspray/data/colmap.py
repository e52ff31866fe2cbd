"""COLMAP sparse reconstructions (through pycolmap): `sparse/0` (or `sparse/`), `images/`, optional `masks/`.

Only undistorted pinhole models are accepted (PINHOLE, SIMPLE_PINHOLE, and radial models whose
distortion parameters are all zero); anything else is refused with the command that undistorts it.
Every `test_every`-th image (sorted by name) is held out as a test view, as LLFF-style evaluations do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from matspray.data.camera import Camera
from matspray.data.images import read_image, srgb_to_linear
from matspray.data.scene import View
from matspray.errors import DataError, file_error

PINHOLE_MODELS = {"PINHOLE", "SIMPLE_PINHOLE"}
ZERO_DISTORTION_MODELS = {"SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"}
MASK_SUFFIXES = (".png", ".jpg", ".jpeg")


def find_model(root: Path) -> Path | None:
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if any((candidate / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            return candidate
    return None


def camera_matrix(camera, model_path: Path) -> torch.Tensor:  # [3, 3]
    name = camera.model_name
    params = [float(p) for p in camera.params]
    if name == "SIMPLE_PINHOLE":
        f, cx, cy = params
        fx = fy = f
    elif name == "PINHOLE":
        fx, fy, cx, cy = params
    elif name in ZERO_DISTORTION_MODELS and all(abs(p) < 1e-12 for p in params[3 if name.startswith("SIMPLE") else 4 :]):
        if name.startswith("SIMPLE") or name == "RADIAL":
            f, cx, cy = params[:3]
            fx = fy = f
        else:
            fx, fy, cx, cy = params[:4]
    else:
        raise file_error(
            model_path,
            f"camera {camera.camera_id} uses the distorted model {name}; MatSpray needs undistorted pinhole images",
            "run 'colmap image_undistorter --image_path images --input_path sparse/0 --output_path undistorted' "
            "and point MatSpray at the 'undistorted' folder",
        )
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float32)


def find_mask(mask_dir: Path, image_name: str) -> Path | None:
    for name in (image_name, Path(image_name).stem):
        for suffix in ("",) + MASK_SUFFIXES:
            candidate = mask_dir / (name + suffix)
            if candidate.is_file():
                return candidate
    return None


def read_colmap(root: Path, test_every: int = 8) -> tuple[list[View], list[View], torch.Tensor, torch.Tensor]:
    """Returns train views, test views, points [P, 3] and their linear colours [P, 3]."""
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
    for image in images:
        camera = reconstruction.cameras[image.camera_id]
        K = camera_matrix(camera, model_path)
        cam_from_world = torch.tensor(image.cam_from_world().matrix(), dtype=torch.float64)  # [3, 4]
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3] = cam_from_world
        image_path = image_dir / image.name
        rgb, alpha = read_image(image_path)
        if rgb.shape[:2] != (camera.height, camera.width):
            raise file_error(image_path, f"image is {rgb.shape[1]}x{rgb.shape[0]} but its COLMAP camera is {camera.width}x{camera.height}")
        if mask_dir.is_dir():
            mask_path = find_mask(mask_dir, image.name)
            if mask_path is None:
                raise file_error(mask_dir, f"no mask for image '{image.name}'", "give every image a mask or remove masks/")
            mask_rgb, _ = read_image(mask_path)
            alpha = mask_rgb.mean(-1)
            if alpha.shape != rgb.shape[:2]:
                raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
        views.append(View(Path(image.name).stem, rgb, alpha, Camera(K, viewmat.float(), camera.width, camera.height), image_path))
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
    return train, test, points, colors
