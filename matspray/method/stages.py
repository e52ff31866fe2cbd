"""The work of each stage, as functions of what it reads: `Pipeline` decides when a stage runs (its fingerprint, its
record, resuming) and calls these for what it does. Each writes its artifact into the run folder and returns the
(settings, record) pair that the stage's record keeps."""

from __future__ import annotations

from pathlib import Path

import torch

from matspray.data.images import save_torch_atomic
from matspray.data.scene import Scene
from matspray.data.triangulate import points_stage
from matspray.errors import RunError
from matspray.geometry.region import ObjectRegion
from matspray.method.lift import LiftConfig, lift, save_lift
from matspray.method.masks import compute_object_masks, read_region, write_object_masks
from matspray.method.refine.loop import RefineInputs
from matspray.predictors import (
    PredictorOptions,
    make_predictor,
    maps_to_tensor,
    predict_views,
    predicted_normal_maps,
    write_materials2d,
)
from matspray.render.shade.visibility import VisibilityConfig, bake_visibility
from matspray.rundir import RunDir


def predict_maps(run: RunDir, views: list, predictor: str, options: PredictorOptions, log=print) -> tuple[dict, dict]:
    """The 2D material maps of `views` by `predictor`, written to `materials2d/`."""
    log(f"predict: {predictor} on {len(views)} training views")
    made = make_predictor(predictor, options, notify=log)
    write_materials2d(run.root, predict_views(views, made, notify=log), made.describe())
    used = {k: v for k, v in vars(options).items() if v is not None}  # the configured options and a derived seed
    return {"predictor": predictor, **used}, {}


def points(run: RunDir, fingerprint: str, scene: Scene, config, progress: bool, log=print) -> None:
    """Stage `points` of a capture without masks or points (`config`: the run's PipelineConfig): triangulated until
    it holds as many as the Gaussians start from (`geometry.init_points`), if it can; they become the scene's."""
    points_stage(run, fingerprint, scene, config.points, progress, log, config.geometry.init_points)


def object_masks_of(run: RunDir, gaussians, scene: Scene, bounds, progress: bool) -> tuple[dict, dict]:
    """A capture without masks: the object region of the trained Gaussians and every view's mask, to `masks/`."""
    focused = read_region(run.path("geometry"))  # None: the geometry did not focus
    masks = compute_object_masks(gaussians, scene, bounds, progress=progress, region=focused)
    write_object_masks(run.path("masks"), masks)
    return {"object_bounds": bounds}, {"region": masks.region.to_json(), "inside": int(masks.inside.sum())}


def lift_values(views: list, maps: dict | None, device: torch.device) -> list[torch.Tensor]:
    """The values lifted from each view: its 2D maps [H, W, 5], zeros where the run has none."""
    if maps is None:
        return [torch.zeros(v.height, v.width, 5, device=device) for v in views]
    return [maps_to_tensor(maps[v.name]).to(device) for v in views]


def lift_maps(
    path: Path, gaussians, views: list, values: list, config: LiftConfig, progress: bool, log=print
) -> tuple[LiftConfig, dict]:
    """Lift `values` (one [H, W, 5] per view) onto `gaussians`, saved to `path`."""
    device = gaussians.means.device
    cameras = [v.camera.to(device) for v in views]
    alphas = [None if v.alpha is None else v.alpha.to(device) for v in views]
    result = lift(gaussians, cameras, values, alphas, [v.name for v in views], config, progress=progress)
    save_lift(result, path)
    log(f"lift: kept {result.stats['gaussians_kept']} of {result.stats['gaussians_in']} Gaussians")
    return config, {"stats": result.stats}


def bake_to(path: Path, kept, config: VisibilityConfig, progress: bool, log=print) -> tuple[VisibilityConfig, dict]:
    """Directional visibility [N, D] of the Gaussians `kept`, saved to `path`."""
    log(f"visibility: shadow maps of {len(kept)} Gaussians towards {2 * config.rows**2} directions")
    save_torch_atomic(bake_visibility(kept, config, progress=progress).cpu(), path)
    return config, {}


def read_visibility(path: Path, count: int, device: torch.device) -> torch.Tensor:
    """The baked visibility [N, D] at `path`, refused when it was baked for another number of Gaussians."""
    values = torch.load(path, map_location=device)
    if values.shape[0] != count:
        raise RunError(
            f"{path}: visibility of {values.shape[0]} Gaussians, but the lifted geometry has {count}; "
            "delete the file to bake it again"
        )
    return values


def refine_inputs_of(scene: Scene, maps: dict | None, kept, normals, lifted, visibility, device) -> RefineInputs:
    """What refinement reads: the Gaussians `kept` by the lift with their `normals` [N, 3], the lifted values, the
    training views, their 2D maps (none without a predictor) and predicted normals (where the maps have them)."""
    views = [v.to(device) for v in scene.train]
    on_device = None if maps is None else {n: m.to(device) for n, m in maps.items()}
    return RefineInputs(
        gaussians=kept,
        normals=normals,
        values=lifted.values,
        seen=lifted.seen,
        views=views,
        targets=[] if maps is None else [maps_to_tensor(maps[v.name]).to(device) for v in views],
        bounds=scene.bounds.to(device),
        visibility=visibility,
        normal_maps=None if on_device is None else predicted_normal_maps(on_device, views),
    )


def describe_masks(inside: torch.Tensor, region: ObjectRegion) -> str:
    return f"masks: the object is {int(inside.sum())} of {len(inside)} Gaussians, inside the {region.describe()}"
