"""Structure from motion from a folder of photos, with pycolmap on the CPU, into a dataset folder.

Steps: the photos are copied upright (EXIF orientation applied) with their longest side at most
`max_size`; SIFT features are extracted and matched (every pair, or neighbours in file-name order);
incremental mapping registers the photos and triangulates points; the largest model is kept; the
images (and masks) are undistorted to pinhole cameras once, by the loader's undistortion, so `info`
and `run` read the folder at once. The folder is written under a temporary name and renamed when
complete, so a failed or interrupted run leaves nothing half-made:

    DATASET/images/             the photos given to SfM
    DATASET/masks/              (with masks) the masks, sized as the photos
    DATASET/sparse/0/           the COLMAP model (distorted camera, e.g. SIMPLE_RADIAL)
    DATASET/colmap/database.db  features and matches

The undistorted pinhole images the loader reads are cached outside it (matspray.data.undistort.cache_folder).
"""

from __future__ import annotations

import os
import shutil
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image, ImageOps
from tqdm import tqdm

from matspray.data.images import DECODER_ERRORS, atomic_target, read_raw, resize, split_alpha, write_raw
from matspray.data.loader import PHOTO_SUFFIXES, load_scene
from matspray.errors import ConfigError, DataError, file_error, optional_module

MATCHERS = ("exhaustive", "sequential")
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE")  # what SfM may estimate
MIN_REGISTERED = 3
MIN_PHOTO_SIDE = 24  # pixels; below it SIFT finds next to no features (a 2x2 file is a thumbnail or a tracking pixel)
ADVICE = (
    "take more photos with more overlap (every part seen by 3 or more photos, about 15 degrees apart), "
    "keep them sharp and the object textured, or use the exhaustive matcher"
)


@dataclass(frozen=True)
class SfmConfig:
    matcher: str = "exhaustive"  # exhaustive: every pair; sequential: neighbours in file-name order (videos)
    max_size: int = 1600  # longest side of the photos given to SfM (larger ones are shrunk)
    single_camera: bool = False  # one shared camera for every photo (same lens, same zoom)
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP camera model estimated for each camera
    threads: int = -1  # pycolmap threads (-1: all cores)
    seed: int = 0
    # SIFT's contrast threshold, below COLMAP's 0.0067: smooth, weakly textured objects (the back of the skull
    # capture) get enough features to be matched. With guided matching (matches re-searched along the verified
    # epipolar geometry) the skull registered 66 of 66 photos, against 44 of 66 with COLMAP's defaults
    # (docs/dev/real-captures.md).
    peak_threshold: float = 0.004
    guided_matching: bool = True

    def validate(self) -> None:
        if self.camera_model not in CAMERA_MODELS:
            raise ConfigError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}")
        if self.matcher not in MATCHERS:
            raise ConfigError(f"matcher must be one of {', '.join(MATCHERS)}, got {self.matcher!r}")
        if not 0.0 < self.peak_threshold < 0.1:
            raise ConfigError(f"peak_threshold must be in (0, 0.1), got {self.peak_threshold}")
        if not 64 <= self.max_size <= 16384:
            raise ConfigError(f"max_size must be in [64, 16384] pixels, got {self.max_size}")


@dataclass
class SfmResult:
    dataset: Path
    photos: int
    registered: int
    model_sizes: list[int]  # registered photos of every model found, largest first
    mean_reprojection_error: float  # pixels, at the size given to SfM
    points: int
    cameras: list[str]  # one line per estimated camera: model and parameters
    focal: float  # mean focal length (pixels, at the size given to SfM) of the estimated cameras
    seconds: float
    notes: list[str] = field(default_factory=list)


def list_photos(folder: Path) -> list[Path]:
    """The photos in `folder` (not hidden, not in subfolders), sorted; anything else is named and refused."""
    folder = Path(folder)
    if not folder.is_dir():
        raise file_error(folder, "is not a folder of photos" if folder.exists() else "folder does not exist")
    photos, subfolders = [], []
    for path in sorted(folder.iterdir()):
        if path.name.startswith("."):
            continue
        if path.is_dir():
            subfolders.append(path)
            continue
        try:
            path.name.encode("utf-8")
        except UnicodeEncodeError:  # COLMAP keeps image names as UTF-8 text
            raise file_error(path, "has a name that is not valid UTF-8", "rename it") from None
        if path.suffix.lower() not in PHOTO_SUFFIXES:
            raise file_error(
                path,
                f"is not a JPEG or PNG photo ('{path.suffix or 'no suffix'}')",
                "pycolmap reads JPEG and PNG here; convert it or move it out of the folder",
            )
        photos.append(path)
    if len(photos) < MIN_REGISTERED:
        nested = next((d for d in subfolders if any(p.suffix.lower() in PHOTO_SUFFIXES for p in d.iterdir())), None)
        raise file_error(
            folder,
            f"has {len(photos)} photos; structure from motion needs at least {MIN_REGISTERED}",
            f"photos in subfolders are not read: give the folder that holds them, e.g. {nested}"
            if nested is not None
            else "photograph the object from 20 or more directions",
        )
    return photos


def find_photo_mask(mask_dir: Path, photo: Path) -> Path:
    for name in (photo.name, photo.stem):
        for suffix in ("",) + PHOTO_SUFFIXES:
            candidate = mask_dir / (name + suffix)
            if candidate.is_file() and candidate != photo:
                return candidate
    raise file_error(mask_dir, f"has no mask for photo '{photo.name}'", f"expected {mask_dir / (photo.stem + '.png')}")


def sensor_resolution_for(exif, size: tuple[int, int]) -> bool:
    """Make `exif`'s focal plane resolution and pixel dimensions those of the photo written at `size` (width, height);
    True when they changed. pycolmap 4 takes the focal length prior from the focal plane resolution (pixels per unit of
    sensor), which a photo resized before (by its publisher, or here) keeps from the full-size sensor: the prior then
    comes out as many times too long as the photo was shrunk, and the mapper finds no initial pair (the skull's photos).
    """
    inner = exif.get_ifd(0x8769)
    full = (inner.get(0xA002), inner.get(0xA003))  # PixelXDimension, PixelYDimension of the photo as it was shot
    if not all(isinstance(v, int) and v > 0 for v in full) or not inner.get(0xA20E):
        return False
    factor = max(size) / max(full)
    if abs(factor - 1.0) < 1e-3:
        return False
    for tag in (0xA20E, 0xA20F):  # FocalPlaneXResolution, FocalPlaneYResolution
        if inner.get(tag):
            inner[tag] = float(inner[tag]) * factor
    inner[0xA002], inner[0xA003] = (size[0], size[1]) if full[0] >= full[1] else (size[1], size[0])
    return True


def prepare_photo(
    photo: Path, out_dir: Path, max_size: int, mask_dir: Path | None, mask_out: Path | None
) -> tuple[int, int]:
    """Copy one photo upright and at most `max_size` on its longest side (and its mask); returns (width, height)."""
    try:
        with Image.open(photo) as img:
            img.load()
            turned = img.getexif().get(0x0112, 1) not in (None, 1)
            upright = ImageOps.exif_transpose(img) if turned else img
            width, height = upright.size
            if min(width, height) < MIN_PHOTO_SIDE:  # refused here, before structure from motion spends minutes on it
                raise file_error(
                    photo,
                    f"is {width}x{height} pixels; structure from motion needs photos of at least "
                    f"{MIN_PHOTO_SIDE} pixels a side",
                    "use the full-size photos, not thumbnails",
                )
            if upright.mode in (
                "I;16",
                "I;16B",
                "I;16L",
                "I",
            ):  # 16-bit grey: convert("RGB") would clip it at 255, not scale it
                upright = Image.fromarray(
                    np.clip(np.round(np.asarray(upright, dtype=np.float64) / 257.0), 0, 255).astype(np.uint8)
                )
            scale = min(1.0, max_size / max(width, height))
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
            exif = img.getexif()
            stale = sensor_resolution_for(exif, size)
            if (
                scale == 1.0
                and not turned
                and not stale
                and img.mode in ("RGB", "L")
                and img.format in ("JPEG", "MPO", "PNG")
            ):
                shutil.copy2(photo, out_dir / photo.name)  # untouched: keep the file and its EXIF focal length
            else:
                exif[0x0112] = 1  # the pixels are upright now
                picture = upright.convert("RGB").resize(size, Image.Resampling.LANCZOS)
                tmp = atomic_target(out_dir / photo.name)
                picture.save(tmp, quality=95, exif=exif.tobytes()) if photo.suffix.lower() != ".png" else picture.save(
                    tmp
                )
                os.replace(tmp, out_dir / photo.name)
                width, height = size
    except (*DECODER_ERRORS, struct.error, Image.DecompressionBombError) as exc:  # struct.error: a damaged EXIF block
        raise file_error(
            photo, f"cannot read image: {exc or type(exc).__name__}", "pycolmap cannot read it either"
        ) from None
    if mask_dir is not None:
        mask_path = find_photo_mask(mask_dir, photo)
        values = read_raw(mask_path, orient=True)
        rgb, alpha = split_alpha(values)
        mask = alpha if alpha is not None else rgb.mean(-1)
        mh, mw = mask.shape
        if abs(mw * upright.size[1] - mh * upright.size[0]) > 0.01 * mw * upright.size[1]:
            raise file_error(mask_path, f"is {mw}x{mh} but its photo is {upright.size[0]}x{upright.size[1]}")
        write_raw(mask_out / f"{photo.name}.png", resize(mask, height, width))
    return width, height


def prepare_photos(
    photos: list[Path],
    image_dir: Path,
    config: SfmConfig,
    mask_dir: Path | None = None,
    mask_out: Path | None = None,
    progress: bool = False,
) -> dict[str, tuple[int, int]]:
    """Every photo (and mask) prepared into `image_dir` (`prepare_photo`), and their sizes by name: the checks of each
    file that refuse a folder, made before structure from motion starts."""
    sizes = {}
    for photo in tqdm(photos, desc="photos", unit="photo", disable=not progress):
        sizes[photo.name] = prepare_photo(photo, image_dir, config.max_size, mask_dir, mask_out)
    if config.single_camera and len(set(sizes.values())) > 1:
        first = photos[0]
        odd = next(p for p in photos if sizes[p.name] != sizes[first.name])
        raise file_error(
            odd,
            f"is {sizes[odd.name][0]}x{sizes[odd.name][1]} but {first.name} is "
            f"{sizes[first.name][0]}x{sizes[first.name][1]}",
            "one camera for every photo needs photos of one size",
        )
    return sizes


def extract_sift(
    database: Path,
    image_dir: Path,
    names: list[str],
    camera_model: str,
    camera_mode,
    threads: int,
    peak_threshold: float,
    progress: bool,
    desc: str = "SIFT features",
    batch: int = 24,
    first_octave: int = -1,
) -> None:
    """SIFT features of the images `names` of `image_dir` into the COLMAP `database`, on the CPU, `batch` photos a
    call for the progress bar; with a single camera (CameraMode.SINGLE) every batch shares the first one's.
    `first_octave`: -1 (COLMAP's default) starts from the photos at twice their size, 0 at their own. A batch
    is many photos because each call starts its extractor again and ends waiting for its slowest photo with the
    other threads idle (docs/dev/real-captures.md, "SIFT in fewer calls")."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.peak_threshold = peak_threshold
    extraction.sift.first_octave = first_octave
    bar = tqdm(total=len(names), desc=desc, unit="photo", disable=not progress)
    for start in range(0, len(names), batch):
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names[start : start + batch],
            camera_mode=camera_mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        if camera_mode == pycolmap.CameraMode.SINGLE:
            reader.existing_camera_id = 1  # later batches share the first batch's camera
        bar.update(len(names[start : start + batch]))
    bar.close()


def run_sfm(
    images, out, config: SfmConfig = SfmConfig(), masks=None, progress: bool = True, log: Callable[[str], None] = print
) -> SfmResult:
    """Make the dataset folder `out` from the photos in `images` (optional masks in `masks`)."""
    pycolmap = optional_module("pycolmap", "colmap", "structure from motion (`matspray colmap`)")

    config.validate()
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise file_error(out, "already exists and is not empty", "choose another output folder or remove it")
    photos = list_photos(Path(images))
    mask_dir = None if masks is None else Path(masks)
    if mask_dir is not None and not mask_dir.is_dir():
        raise file_error(mask_dir, "mask folder does not exist")
    start = time.perf_counter()
    work = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(work, ignore_errors=True)
    try:
        result = reconstruct(photos, work, config, mask_dir, pycolmap, progress, log)
        if out.exists():
            out.rmdir()
        os.replace(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.dataset = out
    result.notes = [note.replace(str(work.resolve()), str(out.resolve())) for note in result.notes]
    log("undistorting the images ...")
    scene = load_scene(out)  # undistorts into the cache under the dataset's final name, so that later loads read them
    result.notes += [f"loading: {line}" for line in scene.log]  # what `matspray info` prints of the load
    result.seconds = time.perf_counter() - start
    return result


def reconstruct(
    photos: list[Path], work: Path, config: SfmConfig, mask_dir: Path | None, pycolmap, progress: bool, log
) -> SfmResult:
    image_dir, database = work / "images", work / "colmap" / "database.db"
    image_dir.mkdir(parents=True)
    database.parent.mkdir(parents=True)
    mask_out = None
    if mask_dir is not None:
        mask_out = work / "masks"
        mask_out.mkdir()
    prepare_photos(photos, image_dir, config, mask_dir, mask_out, progress)
    pycolmap.logging.minloglevel = 2  # warnings and errors only; progress is ours
    names = [p.name for p in photos]
    mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.AUTO
    extract_sift(database, image_dir, names, config.camera_model, mode, config.threads, config.peak_threshold, progress)
    log(f"matching features ({config.matcher}) ...")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    matching.guided_matching = config.guided_matching
    if config.matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_sequential(database, matching_options=matching, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.threads
    options.random_seed = config.seed
    models_dir = work / "colmap" / "models"
    models_dir.mkdir()
    bar = tqdm(total=len(names), desc="registering photos", unit="photo", disable=not progress)
    models = pycolmap.incremental_mapping(
        database,
        image_dir,
        models_dir,
        options,
        initial_image_pair_callback=lambda: bar.update(2),
        next_image_callback=lambda: bar.update(1),
    )
    bar.close()
    shutil.rmtree(models_dir, ignore_errors=True)
    ranked = sorted(models.values(), key=lambda m: m.num_reg_images(), reverse=True)
    model_sizes = [m.num_reg_images() for m in ranked]
    registered = model_sizes[0] if model_sizes else 0
    if registered < MIN_REGISTERED:
        raise DataError(
            f"{photos[0].parent}: only {registered} of {len(photos)} photos could be registered "
            f"(at least {MIN_REGISTERED} needed); {ADVICE}"
        )
    notes = []
    if len(model_sizes) > 1 and registered < len(photos):  # smaller models of photos the largest holds too say nothing
        notes.append(
            f"the reconstruction split into {len(model_sizes)} parts ({', '.join(map(str, model_sizes))} photos); "
            f"kept the largest: the other photos share too few features with it; {ADVICE}"
        )
    if registered < len(photos):
        kept = {ranked[0].image(i).name for i in ranked[0].reg_image_ids()}
        notes.append(
            f"{len(photos) - registered} photos not registered (left out): {', '.join(sorted(set(names) - kept))}"
        )
    model = ranked[0]
    (work / "sparse" / "0").mkdir(parents=True)
    model.write(str(work / "sparse" / "0"))
    cameras = [
        f"camera {c.camera_id}: {c.model_name} {c.width}x{c.height} " + " ".join(f"{p:.4g}" for p in c.params)
        for c in model.cameras.values()
    ]
    focal = float(np.mean([np.mean([c.params[i] for i in c.focal_length_idxs()]) for c in model.cameras.values()]))
    return SfmResult(
        work,
        len(photos),
        registered,
        model_sizes,
        float(model.compute_mean_reprojection_error()),
        model.num_points3D(),
        cameras,
        focal,
        0.0,
        notes,
    )
