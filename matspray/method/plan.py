"""What a run will compute, before it computes it: the data it reads at the preset's working size, and `resolve_plan`,
a function of the config and the scene that gives each stage's settings as they apply to that data and each stage's
fingerprint (its settings and its upstream stages' fingerprints), as one `RunPlan`. A stage whose files exist with the
same fingerprint is done and reused (`stage_done`); `Pipeline` runs the stages of its plan.

The method (`paper` or `matspray`) is part of the fingerprints of the stages it changes (lift, visibility, refine), so
a run folder resumed with the other method recomputes those and reuses the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.data.crop import CROP_FILE
from matspray.data.scene import Scene, dataset_identity
from matspray.data.triangulate import POINTS_FILE, needs_points
from matspray.errors import file_error
from matspray.geometry.config import GeometryConfig
from matspray.geometry.train import prepare_views
from matspray.method.config import PipelineConfig, variant_refine_config
from matspray.method.estimate import Work, feature_sizes, run_work, view_pixels
from matspray.method.lift import LiftConfig
from matspray.method.merger import mlp_dtype
from matspray.method.refine.loop import RefineConfig
from matspray.predictors import (
    NO_PREDICTOR,
    PredictorOptions,
    options_for_dataset,
    read_predictor_info,
    resolve_predictor,
)
from matspray.presets import VARIANT_NAMES, WORKING_SIZE, asset_stage, get_variant, variants_for_maps
from matspray.rundir import RunDir, fingerprint


@dataclass(frozen=True)
class StageFiles:
    """A stage's folder, the files that must be there (beside its record) for it to count, what "done before" names."""

    folder: str
    files: tuple[str, ...]
    shown: str


STAGES = {  # points and crop run in data.triangulate and method.crop, which say what they reuse themselves
    "points": StageFiles("points", (POINTS_FILE,), "points/"),
    "crop": StageFiles("crop", (CROP_FILE,), "crop/"),
    "predict": StageFiles("materials2d", ("predictor.json",), "materials2d/"),
    "geometry": StageFiles("geometry", ("gaussians.ply",), "geometry/gaussians.ply"),
    "masks": StageFiles("masks", ("masks.pt", "region.json"), "masks/"),
    "lift": StageFiles("lift", ("projected.pt",), "lift/projected.pt"),
    "visibility": StageFiles("visibility", ("visibility.pt",), "visibility/visibility.pt"),
}


def stage_files(stage: str) -> StageFiles:
    """`STAGES[stage]`, or a variant's asset stage (`asset_stage`: asset, asset-no-prior, ...)."""
    return STAGES[stage] if stage in STAGES else StageFiles(stage, ("asset.ply",), f"{stage}/")


def open_scene(data, config: PipelineConfig, log=print) -> tuple[PipelineConfig, Scene]:
    """The dataset at `data`, and `config` resolved against it: photos larger than the preset's working size are
    brought to it unless the config names a downscale, and `auto` becomes a predictor (one that cannot serve these
    views fails here, before any training)."""
    scene = load_scene(data, downscale=config.downscale, max_size=WORKING_SIZE[config.preset])
    if config.downscale is None:
        if scene.downscale > 1.0:
            shown = scene.train[0]
            original = f"{round(shown.width * scene.downscale)}x{round(shown.height * scene.downscale)}"
            log(
                f"photos: {original} brought to {shown.width}x{shown.height}, the {config.preset} preset's "
                "working size (--downscale 1 keeps them as they are)"
            )
        config = replace(config, downscale=scene.downscale)
    return replace(config, predictor=resolve_predictor(config.predictor, scene.train, notify=log)), scene


def light_probe_identity(probe: str | None) -> tuple:
    """What the refinement's fingerprint adds for a light probe: its path, size and time (nothing when unset, so runs
    without one keep their fingerprints). A missing probe fails here, before the run folder is touched."""
    if probe is None:
        return ()
    path = Path(probe)
    if not path.is_file():
        raise file_error(
            path, "the light probe (--set light_probe=PATH) does not exist", "give an HDR lat-long map (.exr or .hdr)"
        )
    stat = path.stat()
    return ({"light_probe": str(path.resolve()), "bytes": stat.st_size, "modified_ns": stat.st_mtime_ns},)


@dataclass(frozen=True)
class StagePlan:
    """One stage as this run will compute it: its settings (as they apply to this scene) and its fingerprint (the
    settings and the upstream stages' fingerprints)."""

    settings: object
    fingerprint: str


@dataclass(frozen=True)
class RunPlan:
    """What a run will compute, resolved once from the config and the scene (`resolve_plan`): each stage's settings and
    fingerprint. The 2D maps' normals are known only once predicted; until then (`normals` None) the stages that follow
    them are None: `geometry`, `masks`, `lift` and `visibility` where the geometry trains on them, `refine` always."""

    config: PipelineConfig
    device: torch.device
    predictor_options: PredictorOptions
    probe: tuple  # the light probe's identity (`light_probe_identity`): the learnt-light variants' fingerprints
    dataset_fp: str
    unmasked: bool  # a capture without masks: its masks come from the geometry (stage `masks`)
    has_maps: bool  # without 2D maps only the variants that need none run
    normals: bool | None  # whether the 2D maps have normal maps; None: not predicted yet
    points_fp: str | None  # a capture without masks or points of its own gets them triangulated (stage `points`)
    crop_fp: str | None  # None where the photos are never cut
    predict: StagePlan
    geometry: StagePlan | None
    masks_fp: str | None
    lift: StagePlan | None
    visibility: StagePlan | None  # also None when shadowing is off (`config.visibility`)
    refine: dict[str, StagePlan] | None  # every variant this run can refine
    merger_dtypes: dict[str, torch.dtype] | None  # what each variant's merger multiplies in on `device`

    @property
    def complete(self) -> bool:
        return self.normals is not None


def _geometry_settings(config: PipelineConfig, unmasked: bool, has_maps: bool, normals) -> GeometryConfig | None:
    """The geometry settings as they apply to this dataset: the object focus only to a capture without masks, the
    predicted normals only where the 2D maps have them (None: not known yet), the material edges where there are maps,
    and neither to a capture without masks, whose masks, which the predictor sees, come from the geometry."""
    geometry = config.geometry.for_scene(masked=not unmasked)
    if geometry.predicted_normal_weight > 0 and not unmasked and normals is None:
        return None  # waits on the predictions
    if geometry.predicted_normal_weight > 0 and (unmasked or not normals):
        geometry = replace(geometry, predicted_normal_weight=0.0)
    if geometry.material_edge_threshold > 0 and (unmasked or not has_maps):
        geometry = replace(geometry, material_edge_threshold=0.0)
    return geometry


def _geometry_plan(geometry: GeometryConfig, dataset_fp: str, predict_fp, points_fp, crop_fp) -> StagePlan:
    """Trained on predicted normals or split on the maps' edges, the geometry depends on the predictions too (a capture
    without masks never is: `predict_fp` may then be None)."""
    on_maps = geometry.predicted_normal_weight > 0 or geometry.material_edge_threshold > 0
    upstream = [predict_fp] if on_maps else []
    upstream += [points_fp] if points_fp else []  # none for masked scenes: their fingerprint is kept
    upstream += [crop_fp] if crop_fp else []
    return StagePlan(geometry, fingerprint("geometry", dataset_fp, geometry.identity(), *upstream))


def _predict_fingerprint(config: PipelineConfig, options: PredictorOptions, dataset_fp: str, masks_fp) -> str:
    masks = () if masks_fp is None else (masks_fp,)  # a capture without masks: the predictor sees the masked views
    seed = options.seed  # an object's own seed changes the draws, except 0 (the default draws)
    derived = () if seed in (config.predictor_options.get("seed"), None, 0) else ({"object_seed": seed},)
    return fingerprint("predict", dataset_fp, config.predictor, config.predictor_options, *masks, *derived)


def _refine_settings(config: PipelineConfig, variant: str, normals: bool) -> RefineConfig:
    """The refinement settings of `variant` in this run: the predicted normals only in a variant that reads the 2D
    maps, and only where they have normal maps."""
    refine = variant_refine_config(config, variant)
    if not (get_variant(variant).uses_maps and refine.predicted_normal_weight > 0 and normals):
        refine = replace(refine, predicted_normal_weight=0.0)
    return refine


def _refine_plans(config: PipelineConfig, device, normals: bool, upstream: tuple, probe: tuple) -> tuple[dict, dict]:
    """Every variant's refinement settings and fingerprint, and its merger's dtype on `device` ("auto" resolved: part
    of the fingerprint). Variants without a light ignore the probe."""
    plans, dtypes = {}, {}
    for variant in VARIANT_NAMES:
        settings = _refine_settings(config, variant, normals)
        dtypes[variant] = mlp_dtype(settings.merger.precision, device)
        probed = probe if get_variant(variant).learns_light else ()
        fp = fingerprint("refine", config.method, settings, str(dtypes[variant]), *upstream, *probed)
        plans[variant] = StagePlan(settings, fp)
    return plans, dtypes


def lift_settings(config: PipelineConfig, has_maps: bool) -> LiftConfig:
    """The lift's settings. A run without 2D maps lifts only to learn which Gaussians the views see (no value is
    read), so one ray per pixel does."""
    return config.lift if has_maps else replace(config.lift, samples_per_side=1)


def resolve_plan(
    config: PipelineConfig, scene: Scene, device: torch.device, normals: bool | None = None, probe: tuple = ()
) -> RunPlan:
    """The plan of `config` over `scene` on `device`: each stage's settings and fingerprint. `normals`: whether the 2D
    maps have normal maps (None: not predicted yet; `with_normals` completes the plan once they are); `probe`: the
    light probe's `light_probe_identity`."""
    options = options_for_dataset(config.predictor, PredictorOptions(**config.predictor_options), scene.source)
    dataset_fp = fingerprint(dataset_identity(scene), config.downscale)
    unmasked, has_maps = not scene.has_masks, config.predictor != NO_PREDICTOR
    # the stage triangulates until it has the points the Gaussians start from (`geometry.init_points`)
    points_fp = (
        fingerprint("points", dataset_fp, config.points, config.geometry.init_points)
        if needs_points(scene, config.points)
        else None
    )
    crop_fp = None
    if unmasked and config.crop.enabled:
        crop_fp = fingerprint("crop", config.crop, config.object_bounds, points_fp or dataset_fp)
    geometry = masks_fp = None
    if unmasked:  # the geometry comes first (it never reads the predictions here), its masks before the predictor
        settings = _geometry_settings(config, True, has_maps, False)
        geometry = _geometry_plan(settings, dataset_fp, None, points_fp, crop_fp)
        masks_fp = fingerprint("masks", config.object_bounds, geometry.fingerprint)
    predict = StagePlan(config.predictor, _predict_fingerprint(config, options, dataset_fp, masks_fp))
    plan = RunPlan(
        config, device, options, probe, dataset_fp, unmasked, has_maps, None, points_fp, crop_fp, predict, geometry,
        masks_fp, None, None, None, None,
    )  # fmt: skip
    plan = _with_geometry(plan, None)
    return with_normals(plan, False) if not has_maps else plan if normals is None else with_normals(plan, normals)


def _with_geometry(plan: RunPlan, normals: bool | None) -> RunPlan:
    """`plan` with the geometry (where it does not wait on unknown normals), the lift and the visibility."""
    config, geometry, masks_fp = plan.config, plan.geometry, plan.masks_fp
    if plan.lift is not None:
        return plan
    if geometry is None:
        settings = _geometry_settings(config, plan.unmasked, plan.has_maps, normals)
        if settings is None:
            return plan  # waits on the predictions' normals
        geometry = _geometry_plan(settings, plan.dataset_fp, plan.predict.fingerprint, plan.points_fp, plan.crop_fp)
        masks_fp = fingerprint("masks", config.object_bounds, geometry.fingerprint)
    at = () if plan.has_maps else ({"views_at": config.geometry.resolution},)
    settings = lift_settings(config, plan.has_maps)
    upstream = (plan.predict.fingerprint, geometry.fingerprint)
    lift = StagePlan(settings, fingerprint("lift", config.method, settings, *upstream, *at))
    visibility = None
    if config.visibility is not None:
        visibility = StagePlan(config.visibility, fingerprint("visibility", config.visibility, lift.fingerprint))
    return replace(plan, geometry=geometry, masks_fp=masks_fp, lift=lift, visibility=visibility)


def with_normals(plan: RunPlan, normals: bool) -> RunPlan:
    """`plan` completed once it is known whether the 2D maps have normal maps: the geometry where it waited on them,
    and every variant's refinement."""
    if plan.complete:
        return plan
    normals = normals and plan.has_maps
    plan = _with_geometry(plan, normals)
    upstream = (plan.lift.fingerprint, None if plan.visibility is None else plan.visibility.fingerprint)
    refine, dtypes = _refine_plans(plan.config, plan.device, normals, upstream, plan.probe)
    return replace(plan, normals=normals, refine=refine, merger_dtypes=dtypes)


def on_geometry(plan: RunPlan, geometry_fp: str) -> RunPlan:
    """`plan` (complete) over the Gaussians of a geometry stage of fingerprint `geometry_fp`, whatever trained them:
    the stages after the geometry follow it. (The benchmarks lift the true maps onto the Gaussians another run
    trained, on its error model's normals, which the truth's own plan knows nothing of.)"""
    geometry = replace(plan.geometry, fingerprint=geometry_fp)
    masks_fp = fingerprint("masks", plan.config.object_bounds, geometry_fp)
    unset = dict(lift=None, visibility=None, refine=None, merger_dtypes=None, normals=None)
    return with_normals(replace(plan, geometry=geometry, masks_fp=masks_fp, **unset), plan.normals)


def plan_for_run(config: PipelineConfig, scene: Scene, device: torch.device, run: RunDir) -> RunPlan:
    """`resolve_plan` for the run folder `run`: the light probe identified (a missing or unreadable one fails here),
    and the 2D maps' normals as a run made before predicted them."""
    plan = resolve_plan(config, scene, device, probe=light_probe_identity(config.light_probe))
    normals = None if plan.complete else recorded_normals(plan, run)
    return plan if normals is None else with_normals(plan, normals)


def stage_done(run: RunDir, stage: str, fp: str | None) -> bool:
    """Whether `stage` (a key of STAGES, or an asset stage) finished in `run` with the fingerprint `fp`."""
    where = stage_files(stage)
    return fp is not None and run.stage_done(where.folder, fp, list(where.files))


def recorded_normals(plan: RunPlan, run: RunDir) -> bool | None:
    """Whether the 2D maps carry normal maps, as their predict stage recorded it in `run`; None until predicted."""
    if not plan.has_maps:
        return False
    if stage_done(run, "predict", plan.predict.fingerprint):
        return "normal_space" in read_predictor_info(run.root)  # recorded with the files
    return None


def lift_views(plan: RunPlan, scene: Scene) -> list:
    """The views lifted from: the training views; without 2D maps, at the size Gaussian Splatting trained at
    (`geometry.resolution`), which is where it decided what each view shows."""
    return scene.train if plan.has_maps else prepare_views(scene.train, plan.config.geometry.resolution)


def lift_pixel_share(plan: RunPlan, scene: Scene) -> float:
    """The lifted views' pixels over the training views' (1 with 2D maps; see `lift_views`)."""
    if plan.has_maps:
        return 1.0
    sizes = [(v.width, v.height) for v in scene.train]
    resolution = plan.config.geometry.resolution
    return sum(view_pixels(w, h, resolution) for w, h in sizes) / sum(w * h for w, h in sizes)


def refine_iterations(plan: RunPlan, variant: str) -> int:
    """The refinement steps of `variant`: the plan's, or before the plan is complete the config's (normals do not
    change them)."""
    return (plan.refine[variant].settings if plan.refine else variant_refine_config(plan.config, variant)).iterations


def estimate_work(plan: RunPlan, scene: Scene, run: RunDir, variants=None) -> Work:
    """What refining `variants` has left to do, for `estimate.estimate_line`. Nothing is computed: predictions not
    made yet leave every refinement to do, and the geometry too where it follows their normals."""
    config = plan.config
    names = variants_for_maps(variants, plan.has_maps)
    stages = {"points": plan.points_fp} if plan.points_fp else {}
    if plan.geometry is not None:
        stages |= {"geometry": plan.geometry.fingerprint, "masks": plan.masks_fp, "lift": plan.lift.fingerprint}
    done = frozenset(stage for stage, fp in stages.items() if stage_done(run, stage, fp))
    pending = plan.refine is None
    to_refine = [v for v in names if pending or not stage_done(run, asset_stage(v), plan.refine[v].fingerprint)]
    feature_views = []  # the photos the `points` stage extracts features from, before the working size
    if plan.points_fp:
        views = [(v.width, v.height) for v in scene.train]
        feature_views = feature_sizes(views, scene.downscale, config.points.max_size)
    return run_work(
        [(v.width, v.height) for v in scene.train],
        config.geometry.iterations,
        config.geometry.resolution,
        lift_settings(config, plan.has_maps).samples_per_side ** 2 * lift_pixel_share(plan, scene),
        [(refine_iterations(plan, v), get_variant(v).uses_maps) for v in to_refine],
        plan.unmasked,
        done,
        feature_views,
    )
