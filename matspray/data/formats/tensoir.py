"""TensoIR layout: `{split}_{i:03d}/metadata.json` and `{split}_{i:03d}/rgba.png` per view.

`metadata.json` holds `cam_transform_mat` (camera-to-world, Blender/OpenGL axes, 16 numbers in
row-major order, as a comma-separated string or a list), `cam_angle_x`, `imw` and `imh`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import torch

from matspray.data.camera import Camera, intrinsics_from_fov, rigid_problem
from matspray.data.formats.blender import check_number, read_json, shown
from matspray.data.images import read_image, resize
from matspray.data.scene import View
from matspray.errors import file_error

_FOLDER = re.compile(r"^(?P<split>[a-z]+)_(?P<index>\d{3,})$")


def view_folders(root: Path, split: str) -> list[Path]:
    folders = []
    for child in root.iterdir():
        match = _FOLDER.match(child.name)
        if match and match.group("split") == split and child.is_dir():
            folders.append((int(match.group("index")), child))
    return [folder for _, folder in sorted(folders)]


def is_tensoir(root: Path) -> bool:
    return any(
        (folder / "metadata.json").exists() for split in ("train", "test") for folder in view_folders(root, split)
    )


def read_split(root: Path, split: str, fit: Callable[[View], View] = lambda view: view) -> list[View]:
    """The split's views, each passed through `fit` as it is read (`loader.WorkingSize`)."""
    return [fit(read_view(folder)) for folder in view_folders(root, split)]


def read_view(folder: Path) -> View:
    meta_path = folder / "metadata.json"
    meta = read_json(meta_path)
    pose = read_pose(meta, meta_path)
    for key in ("cam_angle_x", "imw", "imh"):
        if key not in meta:
            raise file_error(meta_path, f"missing '{key}'")
    fov_x = check_number(meta["cam_angle_x"], "cam_angle_x", "", meta_path, kind="camera_angle_x")
    width, height = (check_number(meta[key], key, "", meta_path, kind="w") for key in ("imw", "imh"))
    image_path = folder / "rgba.png"
    rgb, alpha = read_image(image_path)
    if width != int(width) or height != int(height) or not image_fits(rgb.shape[1], rgb.shape[0], width, height):
        raise file_error(
            meta_path,
            f"imw={shown(meta['imw'])} imh={shown(meta['imh'])} do not fit its image {rgb.shape[1]}x{rgb.shape[0]}",
            "give the size the views are rendered at: whole pixels, the image's aspect ratio",
        )
    width, height = int(width), int(height)
    if rgb.shape[:2] != (height, width):  # metadata is authoritative; images may be stored resized
        rgb = resize(rgb, height, width)
        alpha = None if alpha is None else resize(alpha, height, width)
    K = intrinsics_from_fov(fov_x, width, height)
    if not torch.isfinite(K).all():  # an angle so small that the focal length overflows float32
        raise file_error(meta_path, f"'cam_angle_x' {shown(meta['cam_angle_x'])} gives no finite focal length")
    camera = Camera.from_camtoworld_opengl(pose, K, width, height)
    return View(name=folder.name, image=rgb, alpha=alpha, camera=camera, path=image_path)


def image_fits(image_width: int, image_height: int, width: float, height: float, most: int = 8) -> bool:
    """Whether metadata size (width, height) is the image's aspect ratio (within 1%), at most `most` times its size:
    anything else is a typo, and resizing to it would distort the views or run out of memory."""
    same_shape = abs(image_width * height - image_height * width) <= 0.01 * image_width * height
    return same_shape and width <= most * image_width and height <= most * image_height


def read_pose(meta: dict, meta_path: Path) -> torch.Tensor:  # [4, 4] camera-to-world, OpenGL axes
    pose = meta.get("cam_transform_mat")
    if pose is None:
        raise file_error(meta_path, "no 'cam_transform_mat' (camera pose)")
    try:
        numbers = (
            [float(x) for x in pose.split(",")] if isinstance(pose, str) else torch.tensor(pose).flatten().tolist()
        )
    except (ValueError, TypeError, OverflowError, RuntimeError):
        raise file_error(meta_path, "'cam_transform_mat' is not 16 comma-separated numbers") from None
    if len(numbers) != 16:
        raise file_error(meta_path, f"'cam_transform_mat' has {len(numbers)} numbers, expected 16")
    matrix = torch.tensor(numbers, dtype=torch.float64).reshape(4, 4)
    problem = rigid_problem(matrix)
    if problem:
        raise file_error(
            meta_path,
            f"'cam_transform_mat' is not a rigid camera pose: {problem}",
            "give camera-to-world as rotation and translation only; scale the scene, not the poses",
        )
    return matrix
