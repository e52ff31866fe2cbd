"""TensoIR layout: `{split}_{i:03d}/metadata.json` and `{split}_{i:03d}/rgba.png` per view.

`metadata.json` holds `cam_transform_mat` (camera-to-world, Blender/OpenGL axes, 16 numbers in
row-major order, as a comma-separated string or a list), `cam_angle_x`, `imw` and `imh`.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch

from matspray.data.blender import read_json
from matspray.data.camera import Camera, intrinsics_from_fov
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
    return any((folder / "metadata.json").exists() for split in ("train", "test") for folder in view_folders(root, split))


def read_split(root: Path, split: str) -> list[View]:
    views = []
    for folder in view_folders(root, split):
        meta_path = folder / "metadata.json"
        meta = read_json(meta_path)
        pose = meta.get("cam_transform_mat")
        if pose is None:
            raise file_error(meta_path, "no 'cam_transform_mat' (camera pose)")
        try:
            numbers = [float(x) for x in pose.split(",")] if isinstance(pose, str) else torch.tensor(pose).flatten().tolist()
        except (ValueError, TypeError):
            raise file_error(meta_path, "'cam_transform_mat' is not 16 comma-separated numbers") from None
        if len(numbers) != 16:
            raise file_error(meta_path, f"'cam_transform_mat' has {len(numbers)} numbers, expected 16")
        for key in ("cam_angle_x", "imw", "imh"):
            if key not in meta:
                raise file_error(meta_path, f"missing '{key}'")
        image_path = folder / "rgba.png"
        rgb, alpha = read_image(image_path)
        width, height = int(meta["imw"]), int(meta["imh"])
        if rgb.shape[:2] != (height, width):  # metadata is authoritative; images may be stored resized
            rgb = resize(rgb, height, width)
            alpha = None if alpha is None else resize(alpha, height, width)
        K = intrinsics_from_fov(float(meta["cam_angle_x"]), width, height)
        camera = Camera.from_camtoworld_opengl(torch.tensor(numbers, dtype=torch.float64).reshape(4, 4), K, width, height)
        views.append(View(name=folder.name, image=rgb, alpha=alpha, camera=camera, path=image_path))
    return views
