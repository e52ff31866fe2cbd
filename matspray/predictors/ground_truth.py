"""Ground-truth material maps of a `matspray synth` object, and the `ground-truth` predictor
(benchmarks only: the upper bound that real predictions are compared against).

Next to every view image `{split}/r_000.png` a synth object holds `r_000_basecolor.png` (sRGB-encoded),
`r_000_roughness.png`, `r_000_metallic.png` (linear), `r_000_normal.exr` (world normals) and
`r_000_depth.exr` (camera z along the OpenCV forward axis, 0 on background). The true maps carry the
true normals (world space) where the normal file is there, so that both benchmark predictors pass them on.
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor
from tqdm import tqdm

from matspray.data.images import read_image, read_raw, srgb_to_linear
from matspray.data.scene import View
from matspray.errors import DataError, file_error
from matspray.predictors.base import Predictor
from matspray.predictors.mapfile import read_color_map, read_scalar_map
from matspray.predictors.maps import MaterialMaps
from matspray.predictors.normalmaps import normal_problem, renormalised

SYNTH_HINT = (
    "the simulated and ground-truth predictors need a `matspray synth` object, which stores true maps next to each view"
)


# the truth is compared pixel for pixel, so only at its own size; larger photos are shrunk to a preset's working size
UNSCALED_HINT = "the ground truth is compared at its own size: make the run with --downscale 1 to keep the photos whole"


def ground_truth_path(view: View, what: str) -> Path:
    """`{view}_{what}.png` (or `.exr` for normal and depth) next to the view's image."""
    if view.path is None:
        raise DataError(f"view '{view.name}' has no image path, so its ground truth cannot be found ({SYNTH_HINT})")
    suffix = ".exr" if what in ("normal", "depth") else ".png"
    return Path(view.path).with_name(f"{view.name}_{what}{suffix}")


def check_ground_truth(views: list[View], what: tuple[str, ...] = ("basecolor", "roughness", "metallic")) -> None:
    """DataError naming the views (and dataset) that lack ground-truth files."""
    missing = [v.name for v in views if v.path is None or not all(ground_truth_path(v, w).exists() for w in what)]
    if missing:
        where = next((Path(v.path).parent.parent for v in views if v.path is not None), "the dataset")
        listed = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        raise DataError(
            f"{where}: no ground-truth {'/'.join(what)} maps for {len(missing)} of {len(views)} views "
            f"({listed}); {SYNTH_HINT}"
        )


def read_ground_truth(view: View) -> MaterialMaps:
    """The true maps of one view (base color linear, normals in world space where the object has them),
    checked to match the view's size."""
    stored = read_color_map(ground_truth_path(view, "basecolor"))
    roughness = read_scalar_map(ground_truth_path(view, "roughness"), "roughness")
    metallic = read_scalar_map(ground_truth_path(view, "metallic"), "metallic")
    normals = read_ground_truth_normals(view)
    maps = {"basecolor": stored, "roughness": roughness, "metallic": metallic}
    for what, values in (maps if normals is None else dict(maps, normal=normals)).items():
        if tuple(values.shape[:2]) != (view.height, view.width):
            raise file_error(
                ground_truth_path(view, what),
                f"is {values.shape[1]}x{values.shape[0]} but the view is {view.width}x{view.height}",
                UNSCALED_HINT,
            )
    return MaterialMaps(srgb_to_linear(stored), roughness, metallic, normals=normals, normal_space="world")


def read_ground_truth_normals(view: View) -> Tensor | None:  # [H, W, 3] world, unit or 0; None without the file
    """The true world-space normals `{view}_normal.exr` (the layout `matspray synth` writes), checked."""
    path = ground_truth_path(view, "normal")
    if not path.exists():
        return None
    normals = read_raw(path)[..., :3]
    problem = normal_problem(normals)
    if problem:
        raise file_error(path, problem)
    return renormalised(normals)


def read_ground_truth_coverage(view: View) -> Tensor:  # [H, W] the object's true coverage (its mask)
    """The alpha channel of the true base colour map: the object's coverage, also for photos without masks."""
    path = ground_truth_path(view, "basecolor")
    _, alpha = read_image(path)
    if alpha is None:
        raise file_error(path, "has no alpha channel, so the object's true coverage is unknown")
    return alpha


def read_ground_truth_depth(view: View) -> Tensor:  # [H, W] camera z, 0 on background
    path = ground_truth_path(view, "depth")
    depth = read_raw(path)[..., 0]
    if tuple(depth.shape) != (view.height, view.width):
        raise file_error(
            path, f"is {depth.shape[1]}x{depth.shape[0]} but the view is {view.width}x{view.height}", UNSCALED_HINT
        )
    return depth


class GroundTruthPredictor(Predictor):
    """The true maps, as an upper bound (benchmarks only)."""

    name = "ground-truth"
    benchmark_only = True

    def predict(self, views: list[View]) -> dict[str, MaterialMaps]:
        check_ground_truth(views)
        return {v.name: read_ground_truth(v) for v in tqdm(views, desc="ground truth", unit="view")}
