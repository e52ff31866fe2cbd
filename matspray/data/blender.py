"""Blender / NeRF-synthetic layout: `transforms_{split}.json` plus RGBA images.

Intrinsics come from `camera_angle_x` (square pixels, centred principal point) or from
nerfstudio-style `fl_x, fl_y, cx, cy, w, h`, at the top level or per frame. Poses are
camera-to-world in OpenGL axes and are converted to OpenCV on load. Masks come from the image's
alpha channel, or from a frame's `mask_path` when the images have none.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch

from matspray.data.camera import Camera
from matspray.data.images import atomic_target, read_image, write_image
from matspray.data.scene import View
from matspray.errors import file_error

IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg", ".exr")


def read_json(path: Path) -> dict:
    if not path.exists():
        raise file_error(path, "file does not exist")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise file_error(path, f"malformed JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise file_error(path, f"cannot read: {exc}") from None
    if not isinstance(data, dict):
        raise file_error(path, "expected a JSON object at the top level")
    return data


def resolve_image(root: Path, file_path: str, json_path: Path) -> Path:
    """The image a frame's `file_path` names; NeRF-synthetic omits the suffix, so try the usual ones."""
    base = root / file_path
    for suffix in IMAGE_SUFFIXES:
        candidate = base.with_name(base.name + suffix) if suffix else base
        if candidate.is_file():
            return candidate
    raise file_error(json_path, f"image '{file_path}' of a frame does not exist under {root}")


def view_name(file_path: str) -> str:
    """A view's name: the file name of its `file_path`, without an image suffix."""
    name = Path(str(file_path).replace("\\", "/")).name
    return Path(name).stem if Path(name).suffix.lower() in IMAGE_SUFFIXES else name


def frame_intrinsics(meta: dict, frame: dict, width: int, height: int, json_path: Path, label: str = "") -> torch.Tensor:
    """K [3, 3] for one frame, from per-frame keys first, then the file's top-level keys
    (`label` names the frame in the error when there are none)."""

    def get(key):
        return frame.get(key, meta.get(key))

    w, h = get("w"), get("h")
    sx = width / float(w) if w else 1.0  # intrinsics are given for (w, h); scale to the image read
    sy = height / float(h) if h else 1.0
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
        cx = float(get("cx") if get("cx") is not None else (w or width) / 2.0)
        cy = float(get("cy") if get("cy") is not None else (h or height) / 2.0)
        return torch.tensor([[fx * sx, 0, cx * sx], [0, fy * sy, cy * sy], [0, 0, 1]], dtype=torch.float32)
    if get("camera_angle_x") is not None:
        fx = 0.5 * width / math.tan(0.5 * float(get("camera_angle_x")))
        fy = fx
        if get("camera_angle_y") is not None:
            fy = 0.5 * height / math.tan(0.5 * float(get("camera_angle_y")))
        return torch.tensor([[fx, 0, width / 2.0], [0, fy, height / 2.0], [0, 0, 1]], dtype=torch.float32)
    raise file_error(json_path, f"{label + ' has ' if label else ''}no intrinsics: need 'camera_angle_x' or 'fl_x' "
                     "(with optional fl_y, cx, cy, w, h) in the frame or at the top level")


def read_pose(frame: dict, index: int, json_path: Path) -> torch.Tensor:  # [4, 4] camera-to-world, OpenGL
    matrix = frame.get("transform_matrix")
    if matrix is None:
        raise file_error(json_path, f"frame {index} has no 'transform_matrix' (camera pose)")
    try:
        pose = torch.tensor(matrix, dtype=torch.float64)
    except (TypeError, ValueError):
        raise file_error(json_path, f"frame {index}: 'transform_matrix' is not a 4x4 list of numbers") from None
    if pose.shape == (3, 4):
        pose = torch.cat([pose, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    if pose.shape != (4, 4) or not torch.isfinite(pose).all():
        raise file_error(json_path, f"frame {index}: 'transform_matrix' must be a finite 4x4 matrix, got shape {tuple(pose.shape)}")
    return pose


def read_split(root: Path, split: str) -> list[View]:
    """Views of `transforms_{split}.json` under `root` ([] when the file is absent)."""
    json_path = root / f"transforms_{split}.json"
    if not json_path.exists():
        return []
    meta = read_json(json_path)
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise file_error(json_path, "no 'frames' list")
    views = []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise file_error(json_path, f"frame {index} has no 'file_path'")
        pose = read_pose(frame, index, json_path)
        image_path = resolve_image(root, frame["file_path"], json_path)
        rgb, alpha = read_image(image_path)
        if "mask_path" in frame:
            mask_path = root / frame["mask_path"]
            mask_rgb, mask_alpha = read_image(mask_path)
            alpha = mask_alpha if mask_alpha is not None else mask_rgb.mean(-1)  # linear, 0 and 1 survive
            if alpha.shape != rgb.shape[:2]:
                raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
        height, width = rgb.shape[:2]
        K = frame_intrinsics(meta, frame, width, height, json_path)
        camera = Camera.from_camtoworld_opengl(pose, K, width, height)
        name = view_name(frame["file_path"])
        views.append(View(name=name, image=rgb, alpha=alpha, camera=camera, path=image_path))
    return views


def write_blender(root, splits: dict[str, list[View]], image_format: str = "png") -> None:
    """Write views in the Blender layout: `{split}/{name}.png` (RGBA when alpha exists) and
    `transforms_{split}.json` with full nerfstudio-style intrinsics, so any K round-trips exactly."""
    root = Path(root)
    for split, views in splits.items():
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for view in views:
            relative = f"{split}/{view.name}.{image_format}"
            write_image(root / relative, view.image, view.alpha)
            frames.append({"file_path": f"{split}/{view.name}", **pose_record(view.camera), **intrinsics_record(view.camera)})
        meta = {"frames": frames}
        if views:
            meta["camera_angle_x"] = views[0].camera.fov_x
        write_json(root / f"transforms_{split}.json", meta)


def pose_record(camera: Camera) -> dict:
    """A frame's camera-to-world matrix in OpenGL axes, in float64 so that a reader gets it back exactly."""
    return {"transform_matrix": camera.camtoworld_opengl.double().tolist()}


def intrinsics_record(camera: Camera) -> dict:
    """nerfstudio-style intrinsics of a pinhole camera: any K round-trips exactly."""
    K = camera.K.double()
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": camera.width, "h": camera.height}


def read_scene_json(folder: Path) -> dict | None:
    """The `scene.json` record a `matspray synth` object keeps in its folder: None when there is none,
    {} when it cannot be read as a JSON object."""
    path = Path(folder) / "scene.json"
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


def write_json(path: Path, data) -> None:
    """Write JSON atomically (a reader never sees half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)

