"""Sparse points for a capture that brings none (a `transforms.json` without masks): SIFT features of the training
photos, matched between views that are near in pose, triangulated at the capture's known cameras with pycolmap.

Structure from motion gives a COLMAP dataset its points for free; a capture with known poses has none, and Gaussians
scattered at random in its bounds spend themselves on empty space. Here pycolmap does the same work with the poses
held fixed: the training photos (undistorted on load, so pinhole) are written at a modest size (loaded again when
the run holds them smaller), features are extracted and matched between each view and its `neighbours` nearest
views in pose (not every pair: a video's frames are many, and far-apart views share little), and
`pycolmap.triangulate_points` triangulates the verified matches without moving the cameras. The points are in the
scene's world frame: COLMAP's cam_from_world is our world-to-camera `viewmat` (both OpenCV axes, pixel centres at
+0.5).

SIFT starts at the photos' own scale, not at COLMAP's default of twice it: the doubled octave finds the finest and
most numerous features, which cost most of the extraction and, through their number, most of the matching, while the
Gaussians start from `enough` points at most (`geometry.init_points`). A capture that gives fewer at the photos'
scale (a weakly textured object) is extracted and matched again from twice it (docs/dev/real-captures.md, "SIFT at
the photos' own scale").

In a run (`matspray.method.pipeline`) the result is a stage of its own, `points/points.pt`, so a rerun does not redo it.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from matspray.data.images import SCRATCH_PNG_LEVEL, linear_to_srgb, save_torch_atomic, srgb_to_linear
from matspray.data.scene import MIN_COLMAP_POINTS, Scene, View
from matspray.data.sfm import SfmConfig, extract_sift
from matspray.errors import ConfigError
from matspray.memory import release_free_memory
from matspray.rundir import RunDir, timed
from matspray.settings import setting

STAGE, POINTS_FILE = "points", "points.pt"
# SIFT's first octave (pycolmap's `first_octave`): the photos' own scale, then twice it when that gave too few points
SIFT_OCTAVES = (0, -1)


@dataclass(frozen=True)
class PointsConfig:
    triangulate: bool = setting(
        True,
        "a capture without masks and without points gets points triangulated from its training photos at its "
        "known cameras (off: random points in the bounds)",
    )
    max_size: int = setting(
        1024,
        "longest side of the photos given to feature extraction (loaded again up to this size)",
    )
    neighbours: int = setting(12, "each training view is matched with this many views nearest in pose")
    threads: int = setting(-1, "pycolmap threads (-1: all cores)")

    def __post_init__(self):
        if not 64 <= self.max_size <= 16384:
            raise ConfigError(f"max_size must be in [64, 16384] pixels, got {self.max_size}")
        if self.neighbours < 1:
            raise ConfigError(f"neighbours must be >= 1, got {self.neighbours}")


@dataclass
class Triangulation:
    points: Tensor  # [P, 3] world frame
    colours: Tensor  # [P, 3] linear RGB
    message: str  # one line: what was made, or why there are no points


def needs_points(scene: Scene, config: PointsConfig) -> bool:
    """Whether a run triangulates points for `scene`: a capture without masks and without enough points of its own.
    Masked scenes (every synthetic one) start from their visual hull and are left alone."""
    own = 0 if scene.points is None else len(scene.points)
    return config.triangulate and not scene.has_masks and own < MIN_COLMAP_POINTS


def feature_views(scene: Scene, max_size: int) -> list[View]:
    """The training views at up to `max_size` pixels on their longest side: loaded again from the dataset when the run
    holds them smaller (its working size), since SIFT finds few features on a weakly textured object at that size;
    else the views as the scene holds them. Views loaded again hold 8-bit sRGB images (`srgb8`, what SIFT is given),
    made as each photo is read: stitch's 110 photos of 800 x 800 px took 845 MB as float32, 211 MB so."""
    from matspray.data.loader import load_scene  # the loader's readers import far more than this module needs

    largest = max(max(v.width, v.height) for v in scene.train)
    if scene.source is None or scene.downscale <= 1.0 or largest >= max_size:
        return scene.train
    again = load_scene(scene.source, downscale=None, max_size=max_size, each=srgb8_view)
    larger = {v.name: v for v in again.train}
    if set(larger) != {v.name for v in scene.train}:
        return scene.train
    return [larger[v.name] for v in scene.train]


def srgb8(image: Tensor) -> Tensor:  # [H, W, 3] linear float -> [H, W, 3] uint8 sRGB; uint8 is returned as it is
    if image.dtype == torch.uint8:
        return image
    return (linear_to_srgb(image).clamp(0, 1) * 255).round().to(torch.uint8)


def srgb8_view(view: View) -> View:
    """The view with its image as 8-bit sRGB: the photo as the feature extractor reads it, a quarter of float32's
    memory (the view is no longer a linear float image: only this module's PNG writer reads it)."""
    return View(view.name, srgb8(view.image), None, view.camera, view.path)


def neighbour_pairs(views: list[View], neighbours: int) -> list[tuple[int, int]]:
    """Pairs (i < j) of each view with its `neighbours` nearest views in pose: the distance between camera centres
    (in units of the cameras' spread) plus one minus the cosine between their optical axes."""
    centres = torch.stack([v.camera.center.double().cpu() for v in views])  # [V, 3]
    axes = torch.stack([v.camera.camtoworld.double().cpu()[:3, 2] for v in views])
    axes = axes / axes.norm(dim=-1, keepdim=True)
    spread = (centres - centres.mean(0)).norm(dim=-1).max().clamp_min(1e-9)
    cost = torch.cdist(centres, centres) / spread + (1.0 - axes @ axes.T)  # [V, V]
    cost.fill_diagonal_(float("inf"))
    k = min(neighbours, len(views) - 1)
    nearest = torch.topk(cost, k, dim=1, largest=False).indices if k > 0 else torch.zeros(len(views), 0, dtype=int)
    return sorted({(min(i, int(j)), max(i, int(j))) for i in range(len(views)) for j in nearest[i]})


def triangulate_views(
    views: list[View],
    config: PointsConfig = PointsConfig(),
    progress: bool = False,
    log: Callable[[str], None] = print,
    enough: int = MIN_COLMAP_POINTS,
) -> Triangulation:
    """Points [P, 3] and linear colours [P, 3] triangulated from `views` at their cameras: from SIFT at the photos'
    own scale, or at twice it when that gives fewer than `enough` points (then the pass with more). Never raises for
    what the photos are like: no features, no matches or no pycolmap give no points and a message that says so."""
    try:
        import pycolmap
    except ImportError:
        return _nothing("pycolmap is not installed (pip install 'matspray[colmap]')")
    if len(views) < 2:
        return _nothing(f"{len(views)} training view(s): triangulation needs two or more")
    with tempfile.TemporaryDirectory(prefix="matspray-points-") as work:
        try:
            return _triangulate(pycolmap, [v.to("cpu") for v in views], Path(work), config, enough, progress, log)
        except (RuntimeError, ValueError) as exc:  # pycolmap raises these for what it cannot do with the photos
            return _nothing(f"pycolmap failed: {' '.join(str(exc).split())[:160]}")


def _nothing(reason: str) -> Triangulation:
    return Triangulation(torch.zeros(0, 3), torch.zeros(0, 3), reason)


def _triangulate(
    pycolmap, views: list[View], work: Path, config: PointsConfig, enough: int, progress: bool, log
) -> Triangulation:
    inputs = _pass_inputs(views, work, config)
    pycolmap.logging.minloglevel = 2  # warnings and errors only; progress is ours
    best = None
    for first_octave in SIFT_OCTAVES:
        if best is not None:
            log(
                f"points: {len(best.points)} points from SIFT at the photos' scale, fewer than the {enough} the "
                "Gaussians start from; again from twice the scale ..."
            )
        found = _triangulate_from(pycolmap, inputs, work / f"octave{first_octave}", config, first_octave, progress, log)
        best = found if best is None or len(found.points) > len(best.points) else best
        if len(best.points) >= enough:
            break
    return best


@dataclass(frozen=True)
class _PassInputs:
    """What every pass reads, made once: the photos, their cameras and the pairs of nearby views to match."""

    folder: Path
    names: list[str]  # one PNG per view, in the views' order
    cameras: list  # [Camera] at the PNGs' size
    pairs: list[tuple[int, int]]  # indices into names
    pairs_file: Path  # the pairs by name, as pycolmap imports them


def _pass_inputs(views: list[View], work: Path, config: PointsConfig) -> _PassInputs:
    """The views as 8-bit sRGB PNGs of at most `config.max_size` pixels in work/images, and their nearby pairs."""
    image_dir = work / "images"
    image_dir.mkdir()
    names, cameras = [], []
    for i, view in enumerate(views):
        factor = config.max_size / max(view.width, view.height)
        small = view.scaled(factor) if factor < 1.0 else view
        names.append(f"{i:05d}.png")
        cameras.append(small.camera)
        pixels = srgb8(small.image).numpy()
        Image.fromarray(pixels).save(image_dir / names[-1], compress_level=SCRATCH_PNG_LEVEL)
    pairs = neighbour_pairs(views, config.neighbours)
    (work / "pairs.txt").write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
    return _PassInputs(image_dir, names, cameras, pairs, work / "pairs.txt")


def _triangulate_from(
    pycolmap, inputs: _PassInputs, work: Path, config: PointsConfig, first_octave: int, progress: bool, log
) -> Triangulation:
    """One pass in its own folder `work`: SIFT from `first_octave`, the nearby views' matches, the points."""
    image_dir, names, cameras, pairs = inputs.folder, inputs.names, inputs.cameras, inputs.pairs
    work.mkdir()
    database = work / "database.db"
    # SIFT's threshold as structure from motion's: smooth objects need it
    extract_sift(
        database,
        image_dir,
        names,
        "PINHOLE",
        pycolmap.CameraMode.PER_IMAGE,
        config.threads,
        SfmConfig.peak_threshold,
        progress,
        desc="points: SIFT features" + (" (twice the scale)" if first_octave < 0 else ""),
        first_octave=first_octave,
    )
    with pycolmap.Database.open(database) as db:  # the known intrinsics replace the ones guessed from the files
        ids = {image.name: (image.image_id, image.camera_id) for image in db.read_all_images()}
        for image in db.read_all_images():
            camera, ours = db.read_camera(image.camera_id), cameras[names.index(image.name)]
            K = ours.K.double().cpu()
            camera.params = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
            camera.has_prior_focal_length = True
            db.update_camera(camera)
        if not any(db.num_keypoints_for_image(ids[n][0]) for n in names):
            return _nothing("no features found in the training photos")
    log(f"points: matching {len(pairs)} pairs of nearby views ...")
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.threads
    pycolmap.match_image_pairs(
        database,
        matching_options=matching,
        pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(inputs.pairs_file)),
        device=pycolmap.Device.cpu,
    )
    with pycolmap.Database.open(database) as db:
        if db.num_verified_image_pairs() == 0:
            return _nothing(f"no pair of the {len(pairs)} nearby views shares verified feature matches")
    reconstruction = posed_reconstruction(pycolmap, work, names, ids, cameras)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.threads
    log("points: triangulating at the known cameras ...")
    (work / "model").mkdir()
    model = pycolmap.triangulate_points(
        reconstruction, database, image_dir, work / "model", clear_points=True, options=options, refine_intrinsics=False
    )
    found = list(model.points3D.values())
    if not found:
        return _nothing("the matches triangulated to no points")
    points = torch.from_numpy(np.array([p.xyz for p in found], dtype=np.float32))
    colours = srgb_to_linear(torch.from_numpy(np.array([p.color for p in found], dtype=np.float32)) / 255.0)
    return Triangulation(
        points, colours, f"triangulated {len(found)} points from {len(names)} views ({len(pairs)} pairs matched)"
    )


def posed_reconstruction(pycolmap, work: Path, names: list[str], ids: dict, cameras: list) -> object:
    """A pycolmap Reconstruction with the database's image and camera ids, our pinhole intrinsics and our poses
    (COLMAP's text model read back, which gives each image its trivial rig and frame)."""
    model = work / "posed"
    model.mkdir()
    camera_lines, image_lines = [], []
    for name, camera in zip(names, cameras):
        K = camera.K.double().cpu()
        viewmat = camera.viewmat.double().cpu().numpy()
        quat = pycolmap.Rotation3d(viewmat[:3, :3]).quat  # x, y, z, w
        t = viewmat[:3, 3]
        i, c = ids[name]  # as the database numbers them
        camera_lines.append(
            f"{c} PINHOLE {camera.width} {camera.height} {K[0, 0]:.17g} {K[1, 1]:.17g} {K[0, 2]:.17g} {K[1, 2]:.17g}\n"
        )
        pose = " ".join(f"{v:.17g}" for v in (quat[3], quat[0], quat[1], quat[2], *t))
        image_lines.append(f"{i} {pose} {c} {name}\n\n")
    (model / "cameras.txt").write_text("".join(camera_lines))
    (model / "images.txt").write_text("".join(image_lines))
    (model / "points3D.txt").write_text("")
    return pycolmap.Reconstruction(str(model))


def points_stage(
    run: RunDir,
    fingerprint: str,
    scene: Scene,
    config: PointsConfig,
    progress: bool,
    log: Callable[[str], None],
    enough: int = MIN_COLMAP_POINTS,
) -> Triangulation:
    """The run's stage `points`: `triangulate_views` of the training views (`enough`: the points the Gaussians start
    from, `geometry.init_points`), kept in RUN/points/points.pt (written whole or not at all) and reused while its
    record holds `fingerprint`. With enough points they become the scene's, which the initial Gaussians start from;
    else the scene is left as it is and one line says why."""
    path = run.path(STAGE, POINTS_FILE)
    reused = run.stage_done(STAGE, fingerprint, [POINTS_FILE])
    if reused:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        result = Triangulation(saved["points"], saved["colours"], saved["message"])
    else:
        log(f"points: the capture has no masks and no points; triangulating features of {len(scene.train)} views")
        with timed() as timer:
            views = feature_views(scene, config.max_size)
            release_free_memory()  # what reading the photos again freed, before SIFT's threads allocate beside it
            result = triangulate_views(views, config, progress, log, enough)
            save_torch_atomic({"points": result.points, "colours": result.colours, "message": result.message}, path)
        run.finish_stage(STAGE, fingerprint, config, timer.seconds, {"points": len(result.points)}, timer.peak_mib)
    where = f" (reused {STAGE}/{POINTS_FILE})" if reused else ""
    if len(result.points) < MIN_COLMAP_POINTS:
        log(
            f"points: {result.message}{where}; fewer than {MIN_COLMAP_POINTS} points, so the initial Gaussians are "
            "random points in the bounds"
        )
    else:
        log(f"points: {result.message}{where}")
        scene.points, scene.point_colors = result.points, result.colours
    return result
