"""Find out what layout a dataset folder has, load it as a Scene, and describe it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from matspray.data.crop import CropPlan, read_crop_plan
from matspray.data.formats import blender, colmap, nerfstudio, tensoir
from matspray.data.images import flash_fired
from matspray.data.scene import Scene, View, bounds_from_cameras, bounds_from_points, bounds_from_visual_hull
from matspray.errors import DataError, SettingError, file_error
from matspray.rundir import RunDir

FORMATS = ("blender", "nerfstudio", "tensoir", "colmap")
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")  # what structure from motion (`matspray colmap`) reads


def detect_format(root: Path) -> str:
    root = Path(root)
    if not root.exists():
        raise file_error(root, "path does not exist")
    if not root.is_dir():
        raise file_error(root, "is not a folder", "point at the dataset folder, not a file inside it")
    if (root / "transforms_train.json").exists() or (root / "transforms_test.json").exists():
        return "blender"
    if nerfstudio.is_nerfstudio(root):
        return "nerfstudio"
    if tensoir.is_tensoir(root):
        return "tensoir"
    if colmap.find_model(root) is not None:
        return "colmap"
    photos = photo_folder(root)
    if photos is not None:  # the usual first try: a folder of one's own photos, which have no camera poses yet
        count = len(photo_files(photos))
        where = "" if photos == root else f" in {photos.name}/"
        raise file_error(
            root,
            f"holds {count} photo{'s' * (count != 1)}{where} but no camera poses, so it is not a dataset yet",
            f"`matspray colmap {photos} --out DATA` makes a dataset of them, then `matspray run --data DATA --out RUN`",
        )
    if (root / "dataset.json").is_file():  # `--data RUN` for `--run RUN`: say what it is and where its dataset is
        try:
            hint = f"its dataset is {RunDir(root).dataset()['source']}"
        except DataError:
            hint = "give the dataset folder it was made from"
        raise file_error(root, "is a MatSpray run folder, not a dataset", f"{hint}; a run folder goes to --run")
    tried = (
        "tried blender (transforms_train.json), nerfstudio (transforms.json), tensoir (train_000/metadata.json), "
        "colmap (sparse/0/cameras.bin)"
    )
    raise file_error(root, "no dataset layout recognised", tried)


def photo_files(folder: Path) -> list[Path]:
    """The JPEG and PNG files directly in `folder`."""
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES]


def photo_folder(root: Path) -> Path | None:
    """`root` or its `images` subfolder when it holds JPEG or PNG photos, else None."""
    for folder in (root, root / "images"):
        if folder.is_dir() and photo_files(folder):
            return folder
    return None


def check_split(views: list[View], where: Path, split: str) -> None:
    sizes = {(v.width, v.height) for v in views}
    if len(sizes) > 1:
        first = views[0]
        odd = next(v for v in views if (v.width, v.height) != (first.width, first.height))
        where = odd.path or where
        raise file_error(
            where,
            f"is {odd.width}x{odd.height} but '{first.name}' in the {split} split is {first.width}x{first.height}",
            "all images of a split must have the same size",
        )
    check_alpha(views, where, split)
    names = [v.name for v in views]
    repeated = next((name for name in names if names.count(name) > 1), None)
    if repeated is not None:  # the readers refuse a file that lists a view twice; this is what slips past them
        paths = ", ".join(str(v.path or v.name) for v in views if v.name == repeated)
        raise DataError(f"{where}: the {split} split has {names.count(repeated)} views named '{repeated}' ({paths})")


def check_alpha(views: list[View], where: Path, split: str) -> None:
    """Refuse a split where some views have alpha (or a mask) and others not: the unmasked views' backgrounds
    would be trained as object, and the run fails much later, naming no image."""
    bare = [v for v in views if v.alpha is None]
    if 0 < len(bare) < len(views):
        raise file_error(
            bare[0].path or where,
            f"has no alpha channel or mask, but {len(views) - len(bare)} of the {len(views)} views in the "
            f"{split} split have one "
            f"({len(bare)} have none)",
            "give every view of a split alpha (RGBA images or mask_path) or none of them",
        )


MIN_WORKING_SIDE = 8  # px: a downscale that leaves less is a mistaken factor (1000 made 1 x 1 px views)


class WorkingSize:
    """Brings each view to the working size as the reader makes it, so that a dataset is never held whole at its
    photos' resolution (200 photos of 12 megapixels are 29 GB as float32 RGB). The factor is `downscale`, or with
    `downscale` None the one that brings the first view read to `max_size` on its longest side (1: never enlarged).
    With a `crop` plan each photo is first cut to its window, which then becomes a frame of the plan's size."""

    def __init__(self, downscale: float | None, max_size: int | None, crop: CropPlan | None = None, then=None):
        self.factor = downscale
        self.max_size = max_size
        self.crop = crop
        self.then = then  # View -> View, applied to each view at its working size (load_scene's `each`)

    def __call__(self, view: View) -> View:
        fitted = self._fit(view)
        return fitted if self.then is None else self.then(fitted)

    def _fit(self, view: View) -> View:
        if self.factor is None:
            self.factor = max(1.0, max(view.width, view.height) / self.max_size) if self.max_size else 1.0
        if self.crop is not None:
            return self.crop.fit(view)
        if self.factor == 1.0:
            return view
        scaled = view.scaled(1.0 / self.factor)
        if min(scaled.width, scaled.height) < MIN_WORKING_SIDE:
            raise SettingError(
                "downscale",
                f"{self.factor:g} shrinks {view.name}'s {view.width}x{view.height} image to {scaled.width}x"
                f"{scaled.height} px, under {MIN_WORKING_SIDE} px a side; use a smaller factor (1 keeps the images)",
            )
        return scaled


def load_run_scene(run: RunDir, data=None) -> Scene:
    """The dataset of run folder `run` as its stages saw it: from `data` (default: the folder the run was made from),
    at the run's downscale, each photo cut to the run's crop window when it has them (matspray.data.crop)."""
    source = data if data is not None else run.dataset()["source"]
    return load_scene(source, downscale=run.downscale(), crop=read_crop_plan(run.path("crop")))


def load_scene(
    root,
    downscale: float = 1.0,
    test_every: int = 8,
    max_size: int | None = None,
    crop: CropPlan | None = None,
    each: Callable[[View], View] | None = None,
) -> Scene:
    """Load a dataset folder (Blender, nerfstudio, TensoIR or COLMAP layout) into a Scene.

    `downscale` > 1 shrinks every image and camera by that factor (2 halves the resolution). With `max_size`,
    `downscale` None brings images whose longest side is larger to that size (Scene.downscale says by how much; the
    first view read sets it). Each view is shrunk as it is read (`WorkingSize`); with a `crop` plan it is first cut
    to its window (matspray.data.crop), and every view then has the plan's size. `each` (View -> View) is applied to
    every view once it has that size, before the next is read: a caller that keeps less of each photo (the points
    stage keeps 8-bit images) never holds the whole dataset as float32.
    """
    if downscale is not None and not (math.isfinite(downscale) and downscale >= 1.0):
        raise SettingError("downscale", f"must be a finite number >= 1, got {downscale}")
    root = Path(root)
    fmt = detect_format(root)
    points = colors = None
    log = []
    fit = WorkingSize(downscale, max_size, crop, each)
    if fmt == "blender":
        train, test = blender.read_split(root, "train", fit), blender.read_split(root, "test", fit)
        if not train:
            raise file_error(
                root / "transforms_train.json",
                "has no frames" if (root / "transforms_train.json").exists() else "does not exist",
            )
    elif fmt == "tensoir":
        train, test = tensoir.read_split(root, "train", fit), tensoir.read_split(root, "test", fit)
        if not train:
            raise file_error(root, "TensoIR layout without train_*/ folders")
    elif fmt == "nerfstudio":
        capture = nerfstudio.read_nerfstudio(root, test_every=test_every, fit=fit)
        train, test, log = capture.train, capture.test, capture.notes
        if not train:
            raise file_error(
                root / nerfstudio.TRANSFORMS, "has no train frames", "check train_filenames / test_filenames"
            )
    else:
        train, test, points, colors, log = colmap.read_colmap(root, test_every=test_every, fit=fit)
    for split, views in (("train", train), ("test", test)):
        check_split(views, root, split)
    downscale = fit.factor if fit.factor is not None else 1.0
    views = train + test
    notes = []
    masked = sum(v.alpha is not None for v in views)
    if 0 < masked < len(views):
        notes.append(f"only {masked} of {len(views)} views have masks; masks are ignored for the others")
    bounds = None
    if points is not None and len(points) >= 8:
        bounds = bounds_from_points(points)
    if bounds is None:
        bounds = bounds_from_visual_hull(views)
    if bounds is None:
        bounds = bounds_from_cameras(views)
        notes.append("object bounds guessed from where the cameras look (no masks or points)")
    return Scene(
        train=train,
        test=test,
        bounds=bounds.float(),
        source=root,
        format=fmt,
        points=points,
        point_colors=colors,
        notes=notes,
        log=log,
        downscale=float(downscale),
    )


@dataclass
class SceneSummary:
    lines: list[str]
    problems: list[str]


def describe_scene(scene: Scene) -> SceneSummary:
    """What `matspray info` prints: layout, views, resolution, intrinsics, camera distances, masks."""
    lines = [f"format: {scene.format}", f"source: {scene.source}"] + [f"loading: {line}" for line in scene.log]
    problems = list(scene.notes)
    center = scene.bounds.mean(0)
    for split in ("train", "test"):
        views = scene.split(split)
        if not views:
            lines.append(f"{split}: no views")
            if split == "test":
                problems.append("no test views: evaluation will have nothing to compare against")
            continue
        first = views[0]
        K = first.camera.K
        distances = torch.stack([(v.camera.center - center).norm() for v in views])
        masks = sum(v.alpha is not None for v in views)
        lines += [
            f"{split}: {len(views)} views, {first.width}x{first.height} px",
            f"  intrinsics: fx={float(K[0, 0]):.2f} fy={float(K[1, 1]):.2f} cx={float(K[0, 2]):.2f} "
            f"cy={float(K[1, 2]):.2f}"
            f" (fov_x {first.camera.fov_x * 57.29578:.1f} deg)",
            f"  camera distance to object centre: {float(distances.min()):.3f} .. {float(distances.max()):.3f}",
            f"  masks: {masks} of {len(views)}",
        ]
        flashed = sum(flash_fired(v.path) for v in views)
        if flashed:  # refinement learns a flash at the camera on them (`refine.camera_light` auto)
            lines.append(
                f"  taken with a flash (EXIF): {flashed} of {len(views)}; refinement learns a flash at the camera "
                "for them (--set refine.camera_light=off: it does not)"
            )
        for view in views:
            if view.alpha is not None and float(view.alpha.mean()) < 1e-4:
                problems.append(f"{view.path or view.name}: mask is empty")
            pixels, depth = view.camera.project(center[None])
            x, y = float(pixels[0, 0]), float(pixels[0, 1])
            if float(depth[0]) <= 0 or not (0 <= x < view.width and 0 <= y < view.height):
                problems.append(f"{view.path or view.name}: the object centre is not in front of this camera's image")
    if not any(v.alpha is not None for v in scene.views):
        lines.append(
            "masks: none; after geometry the object is the Gaussians inside an object region (chosen automatically, "
            "or --object-bounds), and their rendered alpha becomes every view's mask (RUN/masks/)"
        )
    lo, hi = scene.bounds.tolist()
    lines.append("object bounds: " + " .. ".join("(" + ", ".join(f"{v:.3f}" for v in b) + ")" for b in (lo, hi)))
    if scene.points is not None:
        lines.append(f"sparse points: {len(scene.points)}")
    return SceneSummary(lines=lines, problems=problems)
