"""Lens distortion: distorted cameras are undistorted once, on load, to pinhole cameras.

A `Lens` holds pinhole intrinsics plus OpenCV distortion coefficients, in the radial-tangential
model (k1, k2, p1, p2, k3, k4, k5, k6; the rational model when k4..k6 are set) or the fisheye model
(k1..k4 on the angle). The pinhole camera it is undistorted to keeps the image size and the principal
point; its focal length is the smallest that leaves no pixel outside the photo, so no black border
reaches training. Images and masks are resampled with OpenCV (`cv2.remap`); the undistorted images of
a dataset (bicubic resampling) are cached as files, so a second load reads them instead of resampling again.

Every K here follows the project's convention (pixel centres at +0.5); OpenCV's has centres at
integer coordinates, so pixel coordinates are shifted by 0.5 on the way to and from OpenCV.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.images import LDR_SUFFIXES, SCRATCH_PNG_LEVEL, read_image, write_image
from matspray.data.scene import View
from matspray.errors import file_error, optional_module
from matspray.files import leftover_temporaries

MIN_KEPT = 0.5  # refuse undistortion that keeps less than this fraction of the photo
CACHE_FOLDER = "matspray-undistorted"
RADTAN_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
FISHEYE_NAMES = ("k1", "k2", "k3", "k4")


@dataclass(frozen=True)
class Lens:
    """A camera as a file describes it: pinhole intrinsics (pixel centres at +0.5) and distortion."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    coeffs: tuple[float, ...] = ()  # radial-tangential: RADTAN_NAMES order; fisheye: FISHEYE_NAMES order
    fisheye: bool = False
    model: str = "PINHOLE"  # the model's name in the file, for messages

    @classmethod
    def from_K(cls, K, width: int, height: int, coeffs=(), fisheye: bool = False, model: str = "PINHOLE") -> "Lens":
        """The lens of the pinhole intrinsics K ([3, 3]) of a width x height image, with distortion `coeffs`."""
        return cls(
            float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height, coeffs, fisheye, model
        )

    @property
    def K(self) -> Tensor:  # [3, 3]
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float32)

    @property
    def distorted(self) -> bool:
        return any(c != 0.0 for c in self.coeffs)

    def describe(self) -> str:
        names = FISHEYE_NAMES if self.fisheye else RADTAN_NAMES
        terms = " ".join(f"{n}={c:.4g}" for n, c in zip(names, self.coeffs) if c != 0.0)
        return f"{self.model} ({terms or 'no distortion'})"

    def distort(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] normalised pinhole -> [N, 2] normalised distorted
        x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
        if self.fisheye:
            k1, k2, k3, k4 = (tuple(self.coeffs) + (0.0,) * 4)[:4]
            r = np.hypot(x, y)
            theta = np.arctan(r)
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
            scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
            return np.stack([x * scale, y * scale], axis=-1)
        k1, k2, p1, p2, k3, k4, k5, k6 = (tuple(self.coeffs) + (0.0,) * 8)[:8]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] normalised -> [N, 2] pixel coordinates
        return xy * np.array([self.fx, self.fy]) + np.array([self.cx, self.cy])

    def opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """K in OpenCV's pixel convention (centres at integers) and the coefficient vector."""
        K = np.array([[self.fx, 0.0, self.cx - 0.5], [0.0, self.fy, self.cy - 0.5], [0.0, 0.0, 1.0]])
        return K, np.array(self.coeffs if self.coeffs else (0.0,) * 4, dtype=np.float64)

    def undistort_pixels(
        self, pixels: np.ndarray
    ) -> np.ndarray:  # [N, 2] distorted pixels -> [N, 2] normalised pinhole
        cv2 = opencv()
        K, D = self.opencv()
        points = (pixels - 0.5).reshape(-1, 1, 2).astype(np.float64)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
        if self.fisheye:
            out = cv2.fisheye.undistortPoints(points, K, D[:4], criteria=criteria)
        else:
            out = cv2.undistortPoints(points, K, D, criteria=criteria)
        return out.reshape(-1, 2)


@dataclass(frozen=True)
class Undistortion:
    """How one lens is undistorted: the pinhole K [3, 3] it becomes and where each of its pixels samples."""

    lens: Lens
    K: Tensor  # [3, 3] pinhole intrinsics of the undistorted image (same size as the photo)
    map_x: np.ndarray = field(repr=False)  # [H, W] float32, source column (OpenCV convention) of each output pixel
    map_y: np.ndarray = field(repr=False)  # [H, W] float32
    kept: float = 1.0  # fraction of the photo's area that the undistorted image still shows

    def apply(self, image: Tensor) -> Tensor:  # [H, W, C] or [H, W] -> same shape, resampled
        cv2 = opencv()
        array = np.ascontiguousarray(image.detach().cpu().numpy(), dtype=np.float32)
        # bicubic: closer to the truth than bilinear, with less blur (docs/defaults.md)
        out = cv2.remap(array, self.map_x, self.map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        return torch.from_numpy(out.reshape(array.shape))

    def key(self) -> str:
        """A short fingerprint of the lens and the result, for cache file names."""
        text = repr((self.lens, [round(float(v), 6) for v in self.K.flatten()]))
        return hashlib.sha1(text.encode()).hexdigest()[:12]


def opencv():
    return optional_module("cv2", "captures", "undistorting images")


def output_grid(width: int, height: int) -> np.ndarray:  # [H, W, 2] pixel centres (+0.5 convention)
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([cols, rows], axis=-1)


def border_pixels(width: int, height: int, samples: int = 256) -> np.ndarray:  # [4 * samples, 2]
    u = np.linspace(0.5, width - 0.5, samples)
    v = np.linspace(0.5, height - 0.5, samples)
    return np.concatenate(
        [
            np.stack([u, np.full_like(u, 0.5)], -1),
            np.stack([u, np.full_like(u, height - 0.5)], -1),
            np.stack([np.full_like(v, 0.5), v], -1),
            np.stack([np.full_like(v, width - 0.5), v], -1),
        ]
    )


def source_pixels(lens: Lens, K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Where output pixels [N, 2] of the pinhole K [3, 3] sample the distorted photo: [N, 2] pixels."""
    xy = (pixels - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    return lens.to_pixels(lens.distort(xy))


def inside(pixels: np.ndarray, width: int, height: int) -> np.ndarray:  # [N, 2] -> [N] bool
    return (pixels[:, 0] >= 0) & (pixels[:, 0] <= width) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= height)


def pinhole_for(lens: Lens) -> np.ndarray:
    """The pinhole K [3, 3] (same principal point, focal scaled) whose image border stays inside the photo."""
    base = np.array([[lens.fx, 0.0, lens.cx], [0.0, lens.fy, lens.cy], [0.0, 0.0, 1.0]])
    centre = np.array([lens.cx, lens.cy])
    steps = np.linspace(0.0, 1.0, 129)[:, None, None]
    rays = centre + steps * (border_pixels(lens.width, lens.height, 64) - centre)  # [T, B, 2] centre to border

    def fits(scale: float) -> bool:  # the border lands inside the photo and no ray folds back on the way
        K = base.copy()
        K[0, 0] *= scale
        K[1, 1] *= scale
        source = source_pixels(lens, K, rays.reshape(-1, 2)).reshape(rays.shape)
        outward = np.linalg.norm(source - centre, axis=-1)  # [T, B]
        return bool(inside(source[-1], lens.width, lens.height).all() and (np.diff(outward, axis=0) > 0).all())

    low, high = 0.05, 1.0
    while not fits(high):  # zoom in until the border lands inside the photo
        low, high = high, high * 2.0
        if high > 64:
            raise ValueError("no pinhole camera of this size fits inside the photo")
    if fits(low):
        return base * np.array([[low, 1, 1], [1, low, 1], [1, 1, 1]])
    for _ in range(40):  # the smallest focal that fits: the widest view without black borders
        middle = 0.5 * (low + high)
        low, high = (low, middle) if fits(middle) else (middle, high)
    return base * np.array([[high, 1, 1], [1, high, 1], [1, 1, 1]])


def plan_undistortion(lens: Lens, where) -> Undistortion:
    """Undistortion of `lens`; refused (naming `where`) when it would keep too little of the photo."""
    advice = "check the distortion coefficients and that they are given for this image size"
    try:
        K = pinhole_for(lens)
    except ValueError:
        raise file_error(
            where, f"the {lens.describe()} distortion leaves no undistorted view inside the image", advice
        ) from None
    grid = output_grid(lens.width, lens.height).reshape(-1, 2)
    source = source_pixels(lens, K, grid).reshape(lens.height, lens.width, 2)
    # the area of the photo the output covers: the sum of the map's Jacobian determinants
    du = np.gradient(source, axis=1)
    dv = np.gradient(source, axis=0)
    det = du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]  # [H, W]
    if (det <= 0).mean() > 1e-3:  # a fold inside the image (a few pixels at a corner touching it are tolerated)
        raise file_error(
            where, f"the {lens.describe()} distortion folds over inside the image (not invertible)", advice
        )
    kept = float(det.clip(min=0).sum()) / (lens.width * lens.height)
    if kept < MIN_KEPT:
        raise file_error(
            where,
            f"the {lens.describe()} distortion is so strong that undistortion would keep only "
            f"{100 * kept:.0f}% of the image "
            f"(at least {100 * MIN_KEPT:.0f}% needed)",
            advice,
        )
    map_x = (source[..., 0] - 0.5).astype(np.float32)
    map_y = (source[..., 1] - 0.5).astype(np.float32)
    return Undistortion(lens, torch.tensor(K, dtype=torch.float32), map_x, map_y, min(kept, 1.0))


def distort_image(image: Tensor, lens: Lens, K: Tensor) -> Tensor:
    """What a distorted `lens` would have photographed, from a pinhole image [H, W, C] with intrinsics K [3, 3].

    The inverse of undistortion, for making distorted test captures; pixels that see beyond the
    pinhole image repeat its border.
    """
    cv2 = opencv()
    xy = lens.undistort_pixels(output_grid(lens.width, lens.height).reshape(-1, 2))  # normalised pinhole
    K = K.double().numpy()
    pixels = xy * np.array([K[0, 0], K[1, 1]]) + K[:2, 2] - 0.5
    map_x = pixels[:, 0].reshape(lens.height, lens.width).astype(np.float32)
    map_y = pixels[:, 1].reshape(lens.height, lens.width).astype(np.float32)
    array = np.ascontiguousarray(image.detach().cpu().numpy(), dtype=np.float32)
    out = cv2.remap(array, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out.reshape(array.shape[:2] + array.shape[2:]))


def distort_view(view: View, lens: Lens) -> View:
    """`view` (a pinhole photo and its alpha) as the distorted `lens` would have taken it from the same pose;
    the View keeps the pinhole camera it was made from."""
    alpha = None if view.alpha is None else distort_image(view.alpha, lens, view.camera.K)
    return View(view.name, distort_image(view.image, lens, view.camera.K), alpha, view.camera, view.path)


# ------------------------------------------------------------------------------------------ datasets
def cache_folder(root: Path) -> Path:
    """Where the undistorted images of the dataset at `root` are cached: never in the dataset (it may be read-only,
    and a user's capture folder should not grow), but under $MATSPRAY_CACHE when set, else the user's cache folder
    ($XDG_CACHE_HOME or ~/.cache), else the temporary folder; one subfolder per dataset."""
    root = Path(root).resolve()
    named = os.environ.get("MATSPRAY_CACHE")
    if named:
        base = Path(named).expanduser()
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "matspray"
        if not os.access(_existing_parent(base), os.W_OK):
            base = Path(tempfile.gettempdir()) / "matspray"
    return base / CACHE_FOLDER / f"{root.name}-{hashlib.sha1(str(root).encode()).hexdigest()[:12]}"


def _existing_parent(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


class Undistorter:
    """Turns the views of one dataset into pinhole views: one plan per lens, images cached under `cache`.

    `view(...)` takes a `load()` that returns (rgb [H, W, 3], alpha [H, W] or None) in the lens's frame;
    it is called only when the cache has no current copy of the undistorted view.
    """

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        self.cache = cache_folder(root)
        self.plans: dict[Lens, Undistortion] = {}
        self.undistorted = 0
        self.from_cache = 0
        self.swept = False

    def view(self, name: str, path: Path, lens: Lens, viewmat: Tensor, load: Callable, sources=()) -> View:
        """A pinhole View of the photo at `path` taken with `lens` (world-to-camera `viewmat` [4, 4]);
        `sources` are further files (a mask) whose change must invalidate the cache."""
        if not lens.distorted:
            rgb, alpha = load()
            return View(name, rgb, alpha, Camera(lens.K, viewmat.float(), lens.width, lens.height), path)
        plan = self.plans.get(lens)
        if plan is None:
            plan = self.plans[lens] = plan_undistortion(lens, path)
        camera = Camera(plan.K.clone(), viewmat.float(), lens.width, lens.height)
        if not all(Path(source).is_file() for source in (path, *sources)):
            load()  # names the missing file
        cached = self.cached_path(path, plan, sources)
        if cached.is_file():
            rgb, alpha = read_image(cached)
            self.from_cache += 1
            return View(name, rgb, alpha, camera, path)
        rgb, alpha = load()
        rgb = plan.apply(rgb).clamp_min(0.0)
        alpha = None if alpha is None else plan.apply(alpha).clamp(0.0, 1.0)
        self.undistorted += 1
        if self.store(cached, rgb, alpha):  # what later loads will read, so that every load gives the same values
            rgb, alpha = read_image(cached)
        return View(name, rgb, alpha, camera, path)

    def cached_path(self, path: Path, plan: Undistortion, sources) -> Path:
        stamp = [plan.key()]
        for source in (path, *sources):
            stat = Path(source).stat()
            stamp.append(f"{self.relative(source)}:{stat.st_size}:{stat.st_mtime_ns}")
        digest = hashlib.sha1("|".join(stamp).encode()).hexdigest()[:12]
        origin = hashlib.sha1(self.relative(path).encode()).hexdigest()[:8]  # same stem, other folder
        suffix = ".png" if path.suffix.lower() in LDR_SUFFIXES else ".exr"
        return self.cache / f"{path.stem}-{origin}-{digest}{suffix}"

    def relative(self, path: Path) -> str:
        """`path` relative to the dataset (so that a moved dataset keeps its cache), else absolute."""
        resolved = Path(path).resolve()
        return str(resolved.relative_to(self.root)) if resolved.is_relative_to(self.root) else str(resolved)

    def store(self, cached: Path, rgb: Tensor, alpha: Tensor | None) -> bool:
        try:
            if not self.swept:  # before this load's first write: what killed loads left behind goes
                for leftover in leftover_temporaries(cached.parent):
                    leftover.unlink(missing_ok=True)
                self.swept = True
            for stale in cached.parent.glob(f"{cached.stem.rsplit('-', 1)[0]}-*{cached.suffix}"):  # older versions
                stale.unlink()
            write_image(cached, rgb, alpha, png_level=SCRATCH_PNG_LEVEL)  # atomic: a reader never sees half a file
            return True
        except OSError:
            return False  # a cache that cannot be written only costs time on the next load

    def notes(self) -> list[str]:
        """What `matspray info` says about the undistortion."""
        lines = []
        if len(self.plans) > 3:  # one camera per photo (as COLMAP makes them without EXIF): a summary
            plans = list(self.plans.values())
            fx = [float(plan.K[0, 0]) for plan in plans]
            kept = [100 * plan.kept for plan in plans]
            models = ", ".join(sorted({plan.lens.model for plan in plans}))
            lines.append(
                f"undistorted {len(plans)} {models} cameras to pinhole, fx {min(fx):.2f} .. {max(fx):.2f}, "
                f"{min(kept):.0f} .. {max(kept):.0f}% of the image kept"
            )
        for plan in self.plans.values() if len(self.plans) <= 3 else ():
            K = plan.K
            lines.append(
                f"undistorted {plan.lens.describe()} to pinhole fx={float(K[0, 0]):.2f} fy={float(K[1, 1]):.2f} "
                f"cx={float(K[0, 2]):.2f} cy={float(K[1, 2]):.2f}, {100 * plan.kept:.0f}% of the image kept"
            )
        if self.plans:
            lines.append(
                f"undistorted images: {self.undistorted} made, {self.from_cache} read from the cache {self.cache}"
            )
        return lines
