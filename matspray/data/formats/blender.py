"""Blender / NeRF-synthetic layout: `transforms_{split}.json` plus RGBA images.

Intrinsics come from `camera_angle_x` (square pixels, centred principal point) or from
nerfstudio-style `fl_x, fl_y, cx, cy, w, h`, at the top level or per frame. Poses are
camera-to-world in OpenGL axes and are converted to OpenCV on load. Masks come from the image's
alpha channel, or from a frame's `mask_path` when the images have none.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import torch

from matspray.data.camera import Camera, rigid_problem
from matspray.data.formats.repeats import refuse_repeats, without_suffix
from matspray.data.images import read_image, write_image
from matspray.data.scene import View
from matspray.errors import file_error
from matspray.files import write_json

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
    if base.name in ("", ".", ".."):  # '/', '.', 'images/..': a folder, not a file
        raise file_error(json_path, f"image '{file_path}' of a frame names a folder, not an image file")
    for suffix in IMAGE_SUFFIXES:
        candidate = base.with_name(base.name + suffix) if suffix else base
        if candidate.is_file():
            return candidate
    raise file_error(json_path, f"image '{file_path}' of a frame does not exist under {root}")


def view_name(file_path: str) -> str:
    """A view's name: the file name of its `file_path`, without an image suffix."""
    name = Path(str(file_path).replace("\\", "/")).name
    return Path(name).stem if Path(name).suffix.lower() in IMAGE_SUFFIXES else name


# Ranges (open intervals) of the numbers a frame's camera takes; keys not listed (cx, cy, distortion
# coefficients) need only be finite. A zero or negative focal length, or a field of view of 180 degrees
# or more, still gives a K that renders, so without these checks training runs on and learns nonsense.
NUMBER_RANGES = {
    "fl_x": (0.0, math.inf),
    "fl_y": (0.0, math.inf),
    "w": (0.0, math.inf),
    "h": (0.0, math.inf),
    "camera_angle_x": (0.0, math.pi),
    "camera_angle_y": (0.0, math.pi),
}
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
FIX_HINT = "fix the file, or the exporter that wrote it"
REPEAT_HINT = "list each view once: remove the repeated frames"


def frame_label(frame: dict, index: int) -> str:
    """How messages name a frame: its index, and its file_path when it has one."""
    file_path = frame.get("file_path") if isinstance(frame, dict) else None
    return f"frame {index} ('{file_path}')" if isinstance(file_path, str) else f"frame {index}"


def shown(value, limit: int = 40) -> str:
    """A JSON value as it appears in the file, cut short for a one-line message."""
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_number(value) -> float | None:
    """`value` as a float, None when it is no number. A numeric string ("50.0") counts, as nerfstudio's
    own float() reads it; booleans, lists and other strings do not."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        return None
    try:
        return float(value)
    except (ValueError, OverflowError):  # "50mm"; an integer too large for a float
        return None


def check_number(value, key: str, where: str, json_path: Path, kind: str = "") -> float:
    """`value` of field `key` as a float, refused unless it is in the range of NUMBER_RANGES[`kind` or `key`];
    `where` ("frame 3 ('a.png'): ", "top-level ") starts the message."""
    low, high = NUMBER_RANGES.get(kind or key, (-math.inf, math.inf))
    number = as_number(value)
    if number is None or not low < number < high:  # NaN fails every comparison; Inf fails the open bound
        need = (
            "a finite number"
            if low == -math.inf
            else "a number > 0"
            if high == math.inf
            else "an angle in radians between 0 and pi"
        )
        raise file_error(json_path, f"{where}'{key}' must be {need}, got {shown(value)}", FIX_HINT)
    return number


def camera_number(meta: dict, frame: dict, key: str, label: str, json_path: Path) -> float | None:
    """A camera field of a frame (its own, else the file's top-level one), checked; None when neither has it."""
    if frame.get(key) is not None:
        return check_number(frame[key], key, f"{label or 'a frame'}: ", json_path)
    if meta.get(key) is not None:
        return check_number(meta[key], key, "top-level ", json_path)
    return None


def frame_intrinsics(
    meta: dict, frame: dict, width: int, height: int, json_path: Path, label: str = ""
) -> torch.Tensor:
    """K [3, 3] for one frame, from per-frame keys first, then the file's top-level keys
    (`label` names the frame in errors)."""

    get = {key: camera_number(meta, frame, key, label, json_path) for key in CAMERA_KEYS}.get
    w, h = get("w"), get("h")
    sx = width / w if w else 1.0  # intrinsics are given for (w, h); scale to the image read
    sy = height / h if h else 1.0
    if get("fl_x") is not None:
        fx = get("fl_x")
        fy = get("fl_y") if get("fl_y") is not None else fx
        cx = get("cx") if get("cx") is not None else (w or width) / 2.0
        cy = get("cy") if get("cy") is not None else (h or height) / 2.0
        K = torch.tensor([[fx * sx, 0, cx * sx], [0, fy * sy, cy * sy], [0, 0, 1]], dtype=torch.float32)
    elif get("camera_angle_x") is not None:
        fx = fy = 0.5 * width / math.tan(0.5 * get("camera_angle_x"))
        if get("camera_angle_y") is not None:
            fy = 0.5 * height / math.tan(0.5 * get("camera_angle_y"))
        K = torch.tensor([[fx, 0, width / 2.0], [0, fy, height / 2.0], [0, 0, 1]], dtype=torch.float32)
    else:
        raise file_error(
            json_path,
            f"{label + ' has ' if label else ''}no intrinsics: need 'camera_angle_x' or 'fl_x' "
            "(with optional fl_y, cx, cy, w, h) in the frame or at the top level",
        )
    # each number is in range, yet extreme ones (fl_x 1e300, an angle of 1e-320) overflow float32 or scale to 0
    if not torch.isfinite(K).all() or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise file_error(
            json_path,
            f"{label or 'a frame'}: its intrinsics give fx={float(K[0, 0]):.4g} fy={float(K[1, 1]):.4g} "
            f"for a {width}x{height} image, not usable focal lengths",
            FIX_HINT,
        )
    return K


def read_pose(frame: dict, index: int, json_path: Path) -> torch.Tensor:  # [4, 4] camera-to-world, OpenGL
    matrix = frame.get("transform_matrix")
    if matrix is None:
        raise file_error(json_path, f"frame {index} has no 'transform_matrix' (camera pose)")
    label = frame_label(frame, index)
    try:
        pose = torch.tensor(matrix, dtype=torch.float64)
    except (TypeError, ValueError, OverflowError, RuntimeError):  # ragged lists, strings, integers too large
        raise file_error(json_path, f"{label}: 'transform_matrix' is not a 4x4 list of numbers") from None
    if pose.shape == (3, 4):
        pose = torch.cat([pose, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    if pose.shape != (4, 4) or not torch.isfinite(pose).all():
        raise file_error(
            json_path, f"{label}: 'transform_matrix' must be a finite 4x4 matrix, got shape {tuple(pose.shape)}"
        )
    problem = rigid_problem(pose)
    if problem:
        raise file_error(
            json_path,
            f"{label}: 'transform_matrix' is not a rigid camera pose: {problem}",
            "give camera-to-world as rotation and translation only; scale the scene, not the poses",
        )
    return pose


def check_frames(frames: list, json_path: Path) -> None:
    """Every frame is an object with a `file_path`, and no two frames name one image (two frames of one name in
    different folders are two views of one name, which `loader.check_split` refuses within a split)."""
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise file_error(json_path, f"frame {index} has no 'file_path'")
    refuse_repeats(json_path, [without_suffix(frame["file_path"]) for frame in frames], "image", "frames", REPEAT_HINT)


def read_split(root: Path, split: str, fit: Callable[[View], View] = lambda view: view) -> list[View]:
    """Views of `transforms_{split}.json` under `root` ([] when the file is absent), each passed through `fit` as it
    is read (`loader.WorkingSize`)."""
    json_path = root / f"transforms_{split}.json"
    if not json_path.exists():
        return []
    meta = read_json(json_path)
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise file_error(json_path, "no 'frames' list")
    check_frames(frames, json_path)
    views = []
    for index, frame in enumerate(frames):
        label = frame_label(frame, index)
        pose = read_pose(frame, index, json_path)
        image_path = resolve_image(root, frame["file_path"], json_path)
        rgb, alpha = read_image(image_path)
        if frame.get("mask_path") is not None:
            if not isinstance(frame["mask_path"], str):
                raise file_error(
                    json_path, f"{label}: 'mask_path' must be a file path, got {shown(frame['mask_path'])}"
                )
            mask_path = root / frame["mask_path"]
            mask_rgb, mask_alpha = read_image(mask_path)
            alpha = mask_alpha if mask_alpha is not None else mask_rgb.mean(-1)  # linear, 0 and 1 survive
            if alpha.shape != rgb.shape[:2]:
                raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
        height, width = rgb.shape[:2]
        K = frame_intrinsics(meta, frame, width, height, json_path, label)
        camera = Camera.from_camtoworld_opengl(pose, K, width, height)
        name = view_name(frame["file_path"])
        views.append(fit(View(name=name, image=rgb, alpha=alpha, camera=camera, path=image_path)))
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
            frames.append(
                {"file_path": f"{split}/{view.name}", **pose_record(view.camera), **intrinsics_record(view.camera)}
            )
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
    return {
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "w": camera.width,
        "h": camera.height,
    }


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
