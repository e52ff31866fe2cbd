"""COLMAP sparse reconstructions (through pycolmap): `sparse/0` (or `sparse/`), `images/`, optional `masks/`.

Pinhole models are read as they are; distorted ones (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV,
OPENCV_FISHEYE and the radial fisheye models) are undistorted on load, masks the same way
(`matspray.data.undistort`). Every `test_every`-th image (sorted by name) is held out as a test view, as LLFF-style
evaluations do.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from matspray.data.formats.repeats import refuse_repeats
from matspray.data.images import read_image, srgb_to_linear
from matspray.data.scene import View
from matspray.data.undistort import Lens, Undistorter
from matspray.errors import DataError, file_error, optional_module

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
# parameters per COLMAP camera model id (colmap/sensor/models.h)
MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}


def find_model(root: Path) -> Path | None:
    for candidate in (root / "sparse" / "0", root / "sparse"):
        if any((candidate / f"cameras{ext}").exists() for ext in (".bin", ".txt")):
            return candidate
    return None


class _Binary:
    """A cursor over one COLMAP .bin file that refuses, naming the file, what pycolmap would read past the end
    of (pycolmap hangs or crashes on a truncated file or a wrong count)."""

    def __init__(self, path: Path):
        self.path, self.blob, self.at = path, path.read_bytes(), 0

    def read(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.blob):
            raise self.error(f"ends inside {what} (byte {self.at} of {len(self.blob)})")
        values = struct.unpack_from("<" + fmt, self.blob, self.at)
        self.at += size
        return values

    def count(self, what: str, record_bytes: int, fmt: str = "Q") -> int:
        (n,) = self.read(fmt, f"the number of {what}")
        if n * record_bytes > len(self.blob) - self.at:
            raise self.error(f"says it holds {n} {what}, more than its {len(self.blob)} bytes can")
        return n

    def finite(self, values, what: str) -> None:
        if not all(math.isfinite(v) for v in values):
            raise self.error(f"has NaN or Inf in {what}")

    def name(self, what: str) -> str:
        end = self.blob.find(b"\0", self.at)
        if end < 0:
            raise self.error(f"ends inside {what}")
        name, self.at = self.blob[self.at : end].decode("utf-8", "replace"), end + 1
        return name

    def error(self, problem: str) -> DataError:
        return file_error(
            self.path,
            f"is not a valid COLMAP binary model: {problem}",
            "the file is truncated or damaged; export the model again with colmap model_converter",
        )

    def done(self) -> None:
        if self.at != len(self.blob):
            raise self.error(f"has {len(self.blob) - self.at} bytes after its last record")


def check_binary_model(model_path: Path) -> None:
    """Refuse a damaged cameras.bin, images.bin, points3D.bin, rigs.bin or frames.bin (COLMAP 3.12 and later)
    before pycolmap reads it."""
    if (model_path / "cameras.bin").exists():
        file, ids = _Binary(model_path / "cameras.bin"), []
        for i in range(file.count("cameras", 24)):
            camera_id, model_id = file.read("iiQQ", f"camera {i}")[:2]
            if model_id not in MODEL_PARAMS:
                raise file.error(f"camera {camera_id} has the unknown camera model id {model_id}")
            file.read(f"{MODEL_PARAMS[model_id]}d", f"the parameters of camera {camera_id}")
            ids.append(camera_id)
        file.done()
        refuse_repeats(file.path, ids, "camera id", "entries", REPEAT_HINT)
    if (model_path / "images.bin").exists():
        file, ids, names = _Binary(model_path / "images.bin"), [], []
        for i in range(file.count("images", 64)):
            values = file.read("i7di", f"image {i}")
            file.finite(values[1:8], f"the pose of image {values[0]}")
            names.append(file.name(f"the name of image {values[0]}"))
            file.read(f"{file.count(f'points of image {values[0]}', 24) * 3}d", f"the points of image {values[0]}")
            ids.append(values[0])
        file.done()
        refuse_repeated_images(file.path, ids, names)
    if (model_path / "points3D.bin").exists():
        file = _Binary(model_path / "points3D.bin")
        for i in range(file.count("points", 43)):
            values = file.read("Q3d3Bd", f"point {i}")
            file.finite(values[1:4], f"the position of point {values[0]}")
            file.read(f"{2 * file.count(f'track entries of point {values[0]}', 8)}i", f"the track of point {values[0]}")
        file.done()
    if (model_path / "rigs.bin").exists():
        file = _Binary(model_path / "rigs.bin")
        for i in range(file.count("rigs", 8)):
            rig_id, sensors = file.read("II", f"rig {i}")
            if sensors:
                file.read("iI", f"the reference sensor of rig {rig_id}")
            for _ in range(max(0, sensors - 1)):
                if file.read("iIB", f"a sensor of rig {rig_id}")[2]:
                    file.finite(file.read("7d", f"a sensor pose of rig {rig_id}"), f"a sensor pose of rig {rig_id}")
        file.done()
    if (model_path / "frames.bin").exists():
        file = _Binary(model_path / "frames.bin")
        for i in range(file.count("frames", 68)):
            values = file.read("II7d", f"frame {i}")
            file.finite(values[2:], f"the pose of frame {values[0]}")
            file.read(
                "iIQ" * file.count(f"data ids of frame {values[0]}", 16, "I"), f"the data ids of frame {values[0]}"
            )
        file.done()


REPEAT_HINT = "each photo once: rerun COLMAP's mapper, or remove the repeated entries"


def refuse_repeated_images(path: Path, ids: list, names: list[str]) -> None:
    """Two entries of one image id, or one photo under two ids (or two names but the suffix, a.jpg and a.png: one
    view), are refused naming the file; pycolmap keeps one of a repeated id silently, or fails without a word on
    what."""
    refuse_repeats(path, ids, "image id", "entries", REPEAT_HINT)
    refuse_repeats(path, [Path(name).stem for name in names], "photo", "image ids", REPEAT_HINT, labels=ids)


def check_text_ids(model_path: Path) -> None:
    """Refuse a cameras.txt or images.txt that lists one camera or image twice (see refuse_repeated_images)."""
    for name in ("cameras.txt", "images.txt"):
        path = model_path / name
        if not path.exists():
            continue
        try:
            lines = iter(path.read_text(errors="replace").splitlines())
        except OSError as exc:
            raise file_error(path, f"cannot be read ({exc.strerror})") from None
        entries = []
        for line in lines:  # as COLMAP reads them: blank and comment lines skipped, and in images.txt each entry's
            if not line.strip() or line.startswith("#"):  # line is followed by its points' line, blank or not
                continue
            entries.append(line.split())
            if name == "images.txt":
                next(lines, None)
        if name == "cameras.txt":
            refuse_repeats(path, [words[0] for words in entries], "camera id", "entries", REPEAT_HINT)
        else:
            refuse_repeated_images(path, [words[0] for words in entries], [words[-1] for words in entries])


def colmap_lens(camera, model_path: Path) -> Lens:
    """The Lens of a COLMAP camera; models without an OpenCV equivalent are refused, naming the known ones."""
    name = camera.model_name
    if name not in LENSES:
        raise file_error(
            model_path,
            f"camera {camera.camera_id} uses the camera model {name}, which MatSpray cannot undistort",
            f"known: {', '.join(LENSES)}",
        )
    params = [float(p) for p in camera.params]
    try:
        fx, fy, cx, cy, coeffs, fisheye = LENSES[name](params)
    except IndexError:
        raise file_error(model_path, f"camera {camera.camera_id} ({name}) has only {len(params)} parameters") from None
    # a zero, negative or NaN focal length still renders, so training would run on and learn nonsense; the
    # cameras are float32, where 1e-320 is 0 and 1e39 is Inf
    K = torch.tensor([fx, fy, cx, cy], dtype=torch.float32)
    sizes_ok = all(
        1 <= size <= MAX_SIZE for size in (camera.width, camera.height)
    )  # a negative size reads as 2**64 - n
    if (
        not all(math.isfinite(p) for p in params)
        or not (torch.isfinite(K).all() and K[0] > 0 and K[1] > 0)
        or not sizes_ok
    ):
        raise file_error(
            model_path,
            f"camera {camera.camera_id} ({name}) has parameters {', '.join(f'{p:.4g}' for p in params)} "
            f"for {camera.width}x{camera.height} px: focal lengths must be > 0 and every parameter finite",
            "rerun COLMAP's mapper, or fix cameras.txt",
        )
    return Lens(fx, fy, cx, cy, int(camera.width), int(camera.height), tuple(coeffs), fisheye, name)


def find_mask(mask_dir: Path, image_name: str) -> Path | None:
    for name in (image_name, Path(image_name).stem):
        for suffix in ("",) + MASK_SUFFIXES:
            candidate = mask_dir / (name + suffix)
            if candidate.is_file():
                return candidate
    return None


def read_colmap(
    root: Path, test_every: int = 8, fit: Callable[[View], View] = lambda view: view
) -> tuple[list[View], list[View], torch.Tensor, torch.Tensor, list[str]]:
    """Returns train views, test views, points [P, 3], their linear colours [P, 3] and notes on what loading did;
    each view is passed through `fit` as it is read (`loader.WorkingSize`)."""
    pycolmap = optional_module("pycolmap", "colmap", "reading a COLMAP model")

    model_path = find_model(root)
    if model_path is None:
        raise file_error(root, "no COLMAP model found", "expected sparse/0/cameras.bin or sparse/cameras.bin")
    check_binary_model(model_path)
    check_text_ids(model_path)
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
                raise file_error(
                    mask_dir, f"no mask for image '{image.name}'", "give every image a mask or remove masks/"
                )
        load = partial(read_photo, image_path, mask_path, (camera.height, camera.width))
        sources = () if mask_path is None else (mask_path,)
        views.append(fit(undistorter.view(Path(image.name).stem, image_path, lens, viewmat, load, sources)))
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
        raise file_error(
            image_path, f"image is {rgb.shape[1]}x{rgb.shape[0]} but its COLMAP camera is {size[1]}x{size[0]}"
        )
    if mask_path is not None:
        mask_rgb, _ = read_image(mask_path)
        alpha = mask_rgb.mean(-1)
        if alpha.shape != rgb.shape[:2]:
            raise file_error(mask_path, f"mask is {tuple(alpha.shape)} but the image is {tuple(rgb.shape[:2])}")
    return rgb, alpha
