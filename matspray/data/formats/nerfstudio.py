"""nerfstudio / instant-ngp captures: a single `transforms.json` for every frame.

What `ns-process-data` and instant-ngp write: intrinsics at the top level or per frame (`fl_x`,
`fl_y`, `cx`, `cy`, `w`, `h`, or `camera_angle_x`/`_y`), `camera_model` PINHOLE, SIMPLE_PINHOLE,
OPENCV (k1, k2, k3, p1, p2) or OPENCV_FISHEYE (k1..k4), `file_path` with or without its extension,
optional `mask_path`, and optional `train_filenames` / `val_filenames` / `test_filenames`. Poses
are camera-to-world in OpenGL axes, as in Blender files. Without split lists every `test_every`-th
frame (sorted by file path) is held out for testing, as for COLMAP. Distorted cameras are
undistorted on load (`matspray.data.undistort`). Photos are turned upright by their EXIF orientation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from matspray.data.camera import Camera
from matspray.data.formats.blender import (
    CAMERA_KEYS,
    REPEAT_HINT,
    camera_number,
    check_frames,
    frame_intrinsics,
    frame_label,
    intrinsics_record,
    pose_record,
    read_json,
    read_pose,
    resolve_image,
    shown,
    view_name,
)
from matspray.data.formats.repeats import normalised, refuse_repeats, without_suffix
from matspray.data.images import image_size, read_image, read_raw, split_alpha, write_image, write_raw
from matspray.data.scene import View
from matspray.data.undistort import Lens, Undistorter
from matspray.errors import file_error
from matspray.files import write_json

TRANSFORMS = "transforms.json"
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
INTRINSIC_KEYS = CAMERA_KEYS
SPLIT_KEYS = ("train_filenames", "val_filenames", "test_filenames")
FRAME_KEYS = {"file_path", "transform_matrix", "mask_path", "camera_model", *INTRINSIC_KEYS, *DISTORTION_KEYS}
TOP_KEYS = {"frames", "camera_model", *INTRINSIC_KEYS, *DISTORTION_KEYS, *SPLIT_KEYS}
IGNORED_KEYS = {  # known keys that change nothing here, and why
    "applied_transform": "the poses are used as written (nerfstudio stores them with it applied)",
    "aabb_scale": "instant-ngp's scene box; object bounds come from masks, points or cameras",
}


@dataclass
class Capture:
    train: list[View]
    test: list[View]
    notes: list[str] = field(default_factory=list)  # what loading did and what it ignored


def is_nerfstudio(root: Path) -> bool:
    return (Path(root) / TRANSFORMS).is_file()


def frame_lens(meta: dict, frame: dict, label: str, json_path: Path, width: int, height: int) -> Lens:
    """The camera of one frame (per-frame keys first, then the top level) for its image of width x height."""

    coeffs = {key: camera_number(meta, frame, key, label, json_path) or 0.0 for key in DISTORTION_KEYS}
    model = frame.get("camera_model", meta.get("camera_model"))
    if model is None:  # instant-ngp writes no model: k1.. mean OpenCV's
        model = "OPENCV" if any(coeffs.values()) else "PINHOLE"
    if not isinstance(model, str) or model not in CAMERA_MODELS:
        raise file_error(json_path, f"{label}: unknown camera_model {model!r}", f"known: {', '.join(CAMERA_MODELS)}")
    unused = {
        "PINHOLE": DISTORTION_KEYS,
        "SIMPLE_PINHOLE": DISTORTION_KEYS,
        "OPENCV": ("k4",),
        "OPENCV_FISHEYE": ("p1", "p2"),
    }[model]
    stray = [key for key in unused if coeffs[key] != 0.0]
    if stray:
        raise file_error(
            json_path,
            f"{label}: camera_model {model} has no coefficient {', '.join(stray)}",
            "OPENCV takes k1 k2 k3 p1 p2, OPENCV_FISHEYE k1 k2 k3 k4, PINHOLE none",
        )
    w, h = (camera_number(meta, frame, key, label, json_path) for key in ("w", "h"))
    if w and h and abs(width * h - height * w) > 0.01 * width * h:
        raise file_error(
            json_path,
            f"{label}: its image is {width}x{height} but the file gives w={w} h={h}",
            "EXIF orientation is applied; intrinsics must be for the upright photo",
        )
    K = frame_intrinsics(meta, frame, width, height, json_path, label)
    if model == "OPENCV_FISHEYE":
        values, fisheye = tuple(coeffs[k] for k in ("k1", "k2", "k3", "k4")), True
    else:
        values, fisheye = tuple(coeffs[k] for k in ("k1", "k2", "p1", "p2", "k3")), False
    return Lens.from_K(K, width, height, values, fisheye, model)


def assign_splits(
    meta: dict, paths: list[str], json_path: Path, test_every: int
) -> tuple[list[int], list[int], list[str]]:
    """Indices (into `paths`, sorted) of the train and test frames, and notes on frames left out."""
    lookup = {}
    for i, path in enumerate(paths):
        lookup[normalised(path)] = i
        lookup.setdefault(without_suffix(path), i)
    lists = {}
    for key in SPLIT_KEYS:
        if key not in meta:
            continue
        names = meta[key]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise file_error(json_path, f"'{key}' must be a list of file paths")
        refuse_repeats(json_path, [without_suffix(name) for name in names], "frame", f"'{key}' entries", REPEAT_HINT)
        chosen = []
        for name in names:
            index = lookup.get(normalised(name), lookup.get(without_suffix(name)))
            if index is None:
                raise file_error(json_path, f"'{key}' names '{name}', which is no frame's file_path")
            chosen.append(index)
        lists[key] = chosen
    notes = []
    if not lists:
        if test_every > 0 and len(paths) > 1:
            test = [i for i in range(len(paths)) if i % test_every == 0]
        else:
            test = []
        return [i for i in range(len(paths)) if i not in set(test)], test, notes
    test_key = "test_filenames" if "test_filenames" in lists else "val_filenames" if "val_filenames" in lists else None
    test = lists[test_key] if test_key else []
    if test_key == "test_filenames" and "val_filenames" in lists:
        notes.append(f"val_filenames ({len(lists['val_filenames'])} frames) not used: test views are test_filenames")
    held = set(test) | set(lists.get("val_filenames", []))
    train = lists.get("train_filenames", [i for i in range(len(paths)) if i not in held])
    unused = len(paths) - len(set(train) | set(test) | held)
    if unused:
        notes.append(f"{unused} frames are in no split list and are not used")
    if set(train) & set(test):
        notes.append(f"{len(set(train) & set(test))} frames are both train and test views")
    return train, test, notes


def key_notes(meta: dict, frames: list[dict]) -> list[str]:
    notes = [f"ignored '{key}': {why}" for key, why in IGNORED_KEYS.items() if key in meta]
    unknown = sorted(set(meta) - TOP_KEYS - set(IGNORED_KEYS))
    if unknown:
        notes.append(f"ignored unknown keys: {', '.join(unknown)}")
    frame_unknown = sorted({key for frame in frames for key in frame} - FRAME_KEYS)
    if frame_unknown:
        notes.append(f"ignored unknown frame keys: {', '.join(frame_unknown)}")
    return notes


def read_nerfstudio(root, test_every: int = 8, fit: Callable[[View], View] = lambda view: view) -> Capture:
    """The capture's views (each passed through `fit` as it is read: `loader.WorkingSize`) and notes."""
    root = Path(root)
    json_path = root / TRANSFORMS
    meta = read_json(json_path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise file_error(json_path, "no 'frames' list" if not isinstance(frames, list) else "has no frames")
    check_frames(frames, json_path)
    order = sorted(range(len(frames)), key=lambda i: normalised(frames[i]["file_path"]))
    paths = [frames[i]["file_path"] for i in order]
    train_ids, test_ids, notes = assign_splits(meta, paths, json_path, test_every)
    undistorter = Undistorter(root)
    views = {}
    for position in sorted(set(train_ids) | set(test_ids)):
        index = order[position]
        views[position] = fit(read_frame(root, meta, frames[index], index, json_path, undistorter))
    notes = key_notes(meta, frames) + notes + undistorter.notes()
    return Capture([views[i] for i in train_ids], [views[i] for i in test_ids], notes)


def read_frame(root: Path, meta: dict, frame: dict, index: int, json_path: Path, undistorter: Undistorter) -> View:
    label = frame_label(frame, index)
    pose = read_pose(frame, index, json_path)
    image_path = resolve_image(root, frame["file_path"], json_path)
    if frame.get("mask_path") is not None and not isinstance(frame["mask_path"], str):
        raise file_error(json_path, f"{label}: 'mask_path' must be a file path, got {shown(frame['mask_path'])}")
    mask_path = root / frame["mask_path"] if frame.get("mask_path") else None
    if mask_path is not None and not mask_path.is_file():
        raise file_error(json_path, f"{label}: its mask '{frame['mask_path']}' does not exist under {root}")
    width, height = image_size(image_path, orient=True)
    lens = frame_lens(meta, frame, label, json_path, width, height)
    viewmat = Camera.from_camtoworld_opengl(pose, lens.K, width, height).viewmat

    def load():
        rgb, alpha = read_image(image_path, orient=True)
        if mask_path is not None:
            mask_rgb, mask_alpha = split_alpha(read_raw(mask_path, orient=True))  # masks hold linear values
            alpha = mask_alpha if mask_alpha is not None else mask_rgb.mean(-1)
            if alpha.shape != rgb.shape[:2]:
                raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
        return rgb, alpha

    name = view_name(frame["file_path"])
    sources = () if mask_path is None else (mask_path,)
    return undistorter.view(name, image_path, lens, viewmat, load, sources)


# ------------------------------------------------------------------------------------------ writing
def lens_record(lens: Lens) -> dict:
    """camera_model and coefficients of `lens` as nerfstudio names them."""
    if lens.fisheye:
        return {
            "camera_model": "OPENCV_FISHEYE",
            **dict(zip(("k1", "k2", "k3", "k4"), (tuple(lens.coeffs) + (0.0,) * 4)[:4])),
        }
    coeffs = (tuple(lens.coeffs) + (0.0,) * 8)[:8]
    if any(coeffs[5:]):
        raise ValueError("nerfstudio's OPENCV model has no k4, k5, k6 (OpenCV's rational terms)")
    return {"camera_model": "OPENCV", **dict(zip(("k1", "k2", "p1", "p2", "k3"), coeffs[:5]))}


def write_nerfstudio(
    root,
    splits: dict[str, list[View]],
    lens: Lens | None = None,
    image_format: str = "png",
    separate_masks: bool = False,
) -> Path:
    """Write views as a nerfstudio capture: `{split}/{name}.{format}`, `transforms.json` with split lists.

    Every view's pinhole intrinsics are written per frame, unless `lens` is given: then it is the one
    camera of every frame (top level), distortion included, and the images are taken to be its photos.
    `separate_masks` writes alpha as `masks/{split}/{name}.png` named by `mask_path` (JPEG has no alpha).
    """
    root = Path(root)
    frames, lists = [], {}
    for split, views in splits.items():
        lists[f"{split}_filenames"] = []
        for view in views:
            relative = f"{split}/{view.name}.{image_format}"
            frame = {"file_path": relative, **pose_record(view.camera)}
            if lens is None:
                frame.update(intrinsics_record(view.camera))
            if view.alpha is not None and separate_masks:
                write_image(root / relative, view.image)
                write_raw(root / f"masks/{split}/{view.name}.png", view.alpha)
                frame["mask_path"] = f"masks/{split}/{view.name}.png"
            else:
                write_image(root / relative, view.image, view.alpha)
            frames.append(frame)
            lists[f"{split}_filenames"].append(relative)
    meta = {}
    if lens is not None:
        meta.update({"fl_x": lens.fx, "fl_y": lens.fy, "cx": lens.cx, "cy": lens.cy, "w": lens.width, "h": lens.height})
        meta.update(lens_record(lens))
    meta["frames"] = frames
    meta.update(lists)
    write_json(root / TRANSFORMS, meta)
    return root / TRANSFORMS
