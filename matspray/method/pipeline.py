"""The whole method as stages over one run directory: predict -> geometry -> lift -> refine.
A capture without masks runs geometry first, then `masks` (the object region and every view's mask,
matspray.geometry.region), then predict on the masked views; only the Gaussians in the region are lifted.

Each stage is skipped when its artifact exists and was made with the same settings (and from the same upstream
artifacts: its fingerprint, `matspray.method.plan`); `timings.json` records the seconds each stage took (the paper's
Table 3). What each stage does is in `matspray.method.stages`.
"""

from __future__ import annotations

import weakref
from functools import partial

import torch

from matspray.data.scene import dataset_identity
from matspray.device import configure_threads, out_of_memory_as_error, resolve_device
from matspray.geometry.ply import read_ply
from matspray.geometry.region import ObjectRegion
from matspray.geometry.train import train_geometry
from matspray.memory import release_free_memory
from matspray.method import stages
from matspray.method.asset import Asset, read_asset, write_asset
from matspray.method.config import PipelineConfig
from matspray.method.crop import crop_stage
from matspray.method.lift import LiftResult, load_lift
from matspray.method.masks import ObjectMasks, read_object_masks
from matspray.method.plan import (
    RunPlan,
    estimate_work,
    lift_views,
    open_scene,
    plan_for_run,
    recorded_normals,
    stage_done,
    stage_files,
    with_normals,
)
from matspray.method.refine.loop import RefineInputs, frozen_views, refine
from matspray.predictors import maps_to_tensor, predicted_normal_maps, read_materials2d, without_normals
from matspray.presets import asset_stage, get_variant, variants_for_maps
from matspray.render.backend import rendering_with, resolve_backend
from matspray.render.numba.backend import compile_in_background
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir, timed


class Pipeline:
    """One run directory and the stages that fill it, as its plan (`plan`, `matspray.method.plan.resolve_plan`)
    says. Every stage method returns its artifact."""

    def __init__(self, data, out, config: PipelineConfig, overwrite=False, progress=True, log=print, wait=False):
        device = resolve_device(config.device)
        configure_threads(device)
        # "torch", "numba" or "gsplat"; fails here, before any work. Every stage renders with it (see _stage)
        self.backend = resolve_backend(config.backend, device, notify=log)
        if self.backend == "numba":  # its kernels compile (a fresh install) or load while the data is read
            compile_in_background()
        config, scene = open_scene(data, config, log)
        release_free_memory()  # the photos read at their full size are freed: their pages leave the process too
        self.config, self.scene, self.device, self.run = config, scene, device, RunDir(out)
        self.plan: RunPlan = plan_for_run(config, scene, device, self.run)  # a missing light probe fails here
        # the probe is read once (the refinement's fingerprint names the file as it was read), before the folder is used
        height = config.refine.envmap_height
        self.probe = None if config.light_probe is None else EnvironmentMap.from_file(config.light_probe, height=height)
        # the folder is this process's while the pipeline lives (or until close()): another process that wants to write
        # it is refused, or with `wait` waits; a pipeline dropped or closed lets it go
        held = self.run.hold(wait=wait, notify=log)
        self._release = weakref.finalize(self, held.release)
        try:
            self.run.claim(dataset_identity(self.scene), overwrite=overwrite)
            self.run.write_config(config)
        except BaseException:
            self.close()
            raise
        self.progress, self.log = progress, log
        self._object_masks: ObjectMasks | None = None
        self._refine_inputs: RefineInputs | None = None  # the upstream stages' artifacts, once read
        self._frozen_views: FrozenViews | None = None  # their blending weights, shared by the variants refined
        self._warmed_lights: dict = {}  # light warm-ups, shared by variants that start alike (refine.warm_up_key)
        self._cropped, self._crop_region = False, None  # whether crop() has run, and the region it cut around
        self._known: set[str] = set()  # stages this pipeline made, or said it reuses: "done before" is said once

    def close(self) -> None:
        """Lets the run folder go (see __init__); the pipeline must not write after this."""
        self._release()

    def __enter__(self) -> "Pipeline":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def has_maps(self) -> bool:
        return self.plan.has_maps

    def resolved(self) -> RunPlan:
        """The plan, complete: the 2D maps are predicted first where it is not yet known whether they have normals
        (the geometry and refinement may follow them)."""
        if not self.plan.complete:
            self.predict()
            self.plan = with_normals(self.plan, recorded_normals(self.plan, self.run))
        return self.plan

    def geometry_plan(self):
        """The geometry's settings and fingerprint: in the plan from the start unless they follow the 2D maps' normals
        (a capture without masks never waits: its predictions come after its geometry)."""
        return self.plan.geometry or self.resolved().geometry

    def work(self, variants=None):
        """What refining `variants` has left to do (`plan.estimate_work`); nothing is computed."""
        return estimate_work(self.plan, self.scene, self.run, variants)

    def _stage(self, stage: str, fp: str, work, before=None, label: str = "") -> bool:
        """How every stage runs, written once. Done before (`done`): said in one line, and nothing runs. Otherwise
        `before()` (what it needs from other stages, outside its timer), then `work(prepared)` (or `work()`) ->
        (settings, record), timed, rendered with the run's backend, out of memory said in one line; the record
        (settings, seconds, what it ran on) is written last, so an interrupted stage never counts as finished. `label`
        names the stage in lines (default `stage`). "Done before" is said once, and never of what this pipeline made
        (the stages ask for each other's artifacts more than once). Returns whether it ran."""
        label, where = label or stage, stage_files(stage)
        if stage_done(self.run, stage, fp):
            if stage not in self._known:
                self.log(f"{label}: done before, reusing {where.shown}")
                self._known.add(stage)
            return False
        prepared = (before(),) if before is not None else ()
        with timed() as timer, rendering_with(self.backend) as use, out_of_memory_as_error(label, self.device):
            settings, record = work(*prepared)
        ran = {"device": str(self.device), "backend": self.backend, "renders": use.used()}  # what each call really used
        self.run.finish_stage(where.folder, fp, settings, timer.seconds, {**record, **ran}, timer.peak_mib)
        self._known.add(stage)
        return True

    def predict(self):
        """The 2D maps of the training views {name: MaterialMaps}; None in a run without a predictor."""
        self.object_masks()
        if not self.has_maps:
            return None
        options = self.plan.predictor_options
        work = partial(stages.predict_maps, self.run, self.scene.train, self.config.predictor, options, self.log)
        self._stage("predict", self.plan.predict.fingerprint, work)
        return read_materials2d(self.run.root, self.scene.train)

    def crop(self) -> ObjectRegion | None:
        """Cut every photo to its object (matspray.data.crop) before the stages that read them: the windows are found
        once (stage `crop`, from the sparse points) and the scene is read again through them. Returns the region the
        windows were found in (the geometry focuses on it), None when the photos are used whole."""
        fp, points_fp = self.plan.crop_fp, self.plan.points_fp
        if fp is None or self._cropped:
            return self._crop_region
        if points_fp and not stage_done(self.run, "crop", fp):
            stages.points(self.run, points_fp, self.scene, self.config, self.progress, self.log)
        self.scene, self._crop_region = crop_stage(
            self.run, fp, self.scene, self.config.crop, self.config.object_bounds, self.log
        )
        self._cropped = True
        release_free_memory()  # the photos read again through their windows, and the uncut scene
        return self._crop_region

    def geometry_normal_targets(self, maps: dict | None = None) -> list[torch.Tensor] | None:
        """The predicted normal maps geometry trains on (world space, per training view), None when it trains on
        none (said in one line where its weight asks for them). `maps`: the 2D maps when the caller has them."""
        if self.geometry_plan().settings.predicted_normal_weight <= 0:
            if self.config.geometry.predicted_normal_weight > 0 and self.has_maps and not self.plan.unmasked:
                self.log(without_normals(self.run.path("materials2d"), "geometry"))
            return None
        views = [v.to(self.device) for v in self.scene.train]
        return predicted_normal_maps({n: m.to(self.device) for n, m in (maps or self.predict()).items()}, views)

    def geometry(self):
        """Trained Gaussians [N] and their oriented normals [N, 3]."""
        focus_region = self.crop()  # the photos are cut to the object first (a capture without masks)
        config, fp = self.geometry_plan().settings, self.geometry_plan().fingerprint
        edges = config.material_edge_threshold > 0

        def inputs():  # the predictions (read once for both uses) and the points, outside the geometry's timer
            self.log(f"geometry: 3D Gaussian Splatting ({self.config.geometry.iterations} iterations)")
            maps = self.predict() if edges or config.predicted_normal_weight > 0 else None
            if self.plan.points_fp and self.scene.points is None:  # (the crop may have read them already)
                stages.points(self.run, self.plan.points_fp, self.scene, self.config, self.progress, self.log)
            material_maps = [maps_to_tensor(maps[v.name]) for v in self.scene.train] if edges else None
            return self.geometry_normal_targets(maps), material_maps

        # the checkpoint carries the fingerprint (`inputs`): one of other predictions or data is trained over, never
        # resumed, though its settings all match; a finished stage of another fingerprint loses its record first, so an
        # interrupted retraining leaves no record that claims its files
        replaced = self.run.stage_fingerprint("geometry") not in (None, fp)

        def train(prepared) -> tuple:
            normal_targets, material_maps = prepared
            if replaced:
                self.run.reopen_stage("geometry")
            train_geometry(
                self.scene,
                config,
                self.run.path("geometry"),
                device=self.device,
                inputs=fp,
                progress=self.progress,
                normal_targets=normal_targets,
                material_maps=material_maps,
                object_bounds=self.config.object_bounds,
                focus_region=focus_region,
            )
            return config, {}

        self._stage("geometry", fp, train, before=inputs)
        gaussians, normals = read_ply(self.run.path("geometry", "gaussians.ply"))
        return gaussians.to(self.device), torch.nn.functional.normalize(normals, dim=-1).to(self.device)

    def object_masks(self) -> ObjectMasks | None:
        """A capture without masks: the object region, which Gaussians it holds, and every view's mask (their
        rendered alpha), which from here on is the views' alpha. None when the dataset has masks."""
        if not self.plan.unmasked or self._object_masks is not None:
            return self._object_masks
        self.crop()  # the masks belong to the cut photos: cut them first, also when the masks are reused

        def masks_of(gaussians) -> tuple[dict, dict]:
            return stages.object_masks_of(self.run, gaussians, self.scene, self.config.object_bounds, self.progress)

        self._stage("masks", self.plan.masks_fp, masks_of, before=lambda: self.geometry()[0])
        masks = self._object_masks = read_object_masks(self.run.path("masks"))
        self.log(stages.describe_masks(masks.inside, masks.region))
        masks.apply(self.scene)
        return masks

    def object_geometry(self):
        """The Gaussians [N] and normals [N, 3] of the object: all of them, or those in a capture's object region."""
        gaussians, normals = self.geometry()
        masks = self.object_masks()
        if masks is None:
            return gaussians, normals
        inside = masks.inside.to(gaussians.means.device)
        return gaussians.subset(inside), normals[inside]

    def lift(self, gaussians, maps) -> LiftResult:
        """Lift the 2D maps onto the Gaussians. Without maps (None) lifting still decides, from the same rays and
        masks, which Gaussians the views see (the kept ones); its values are zeros that no variant reads."""
        path, plan = self.run.path("lift", "projected.pt"), self.resolved()

        def views_and_values() -> tuple[list, list]:
            views = lift_views(plan, self.scene)
            return views, stages.lift_values(views, maps, self.device)

        def lifted(prepared) -> tuple:
            return stages.lift_maps(path, gaussians, *prepared, plan.lift.settings, self.progress, self.log)

        self._stage("lift", plan.lift.fingerprint, lifted, before=views_and_values)
        return load_lift(path, self.device)

    def visibility(self, kept) -> torch.Tensor | None:
        """Directional visibility [N, D] of the lifted Gaussians `kept`, or None when shadowing is off."""
        if self.config.visibility is None:
            return None
        path, config = self.run.path("visibility", "visibility.pt"), self.config.visibility
        baked = partial(stages.bake_to, path, kept, config, self.progress, self.log)
        self._stage("visibility", self.resolved().visibility.fingerprint, baked)
        return stages.read_visibility(path, len(kept), self.device)

    def refine_inputs(self) -> RefineInputs:
        """Predict, geometry, lift and visibility (each reused when done): what refinement reads. Read
        once per Pipeline: the variants of one run share them."""
        if self._refine_inputs is None:
            maps = self.predict() if self.has_maps else None
            gaussians, normals = self.object_geometry()
            lifted = self.lift(gaussians, maps)
            kept, normals = gaussians.subset(lifted.kept), normals[lifted.kept]
            visibility = self.visibility(kept)
            inputs = stages.refine_inputs_of(self.scene, maps, kept, normals, lifted, visibility, self.device)
            if inputs.normal_maps is None and self.config.refine.predicted_normal_weight > 0 and maps is not None:
                self.log(without_normals(self.run.path("materials2d"), "refinement"))
            self._refine_inputs = inputs
        return self._refine_inputs

    def refine(self, variant: str = "full") -> Asset:
        variants_for_maps([variant], self.has_maps)  # a variant that reads 2D maps is refused in a run without them
        planned, stage = self.resolved().refine[variant], asset_stage(variant)
        config = planned.settings
        probe = self.probe if get_variant(variant).learns_light else None  # variants without a light ignore it

        def refined(inputs) -> tuple:
            if self._frozen_views is None and get_variant(variant).trains and config.iterations > 0:
                self._frozen_views = frozen_views(inputs)
            frozen, warmed = self._frozen_views, self._warmed_lights
            result = refine(inputs, config, self.progress, light=probe, frozen=frozen, warmed_lights=warmed)
            write_asset(self.run.path(stage), inputs.gaussians, result)
            precision = str(self.plan.merger_dtypes[variant]).removeprefix("torch.")
            return config, refine_record(result, precision, variant, inputs, config, self.log)

        self._stage(stage, planned.fingerprint, refined, before=self.refine_inputs, label=f"refine [{variant}]")
        return read_asset(self.run.path(stage), device=self.device)

    def run_all(self, variants=None) -> dict:
        """Refine `variants` (default: full, or in a run without 2D maps the variants that need none)."""
        return {variant: self.refine(variant) for variant in variants_for_maps(variants, self.has_maps)}


def refine_record(result, precision: str, variant: str, inputs: RefineInputs, config, log) -> dict:
    """What a refinement stage's record keeps: the loss curves, the frozen views, the merger's precision, and a flash
    learned beside the light (said in one line: on which photos, how strong)."""
    record = {"history": result.history, "frozen_views": result.frozen, "merger_precision": precision}
    flash = result.camera_light
    if flash is None:
        return record
    lit = result.flash_views
    intensity = [round(float(x), 4) for x in flash.intensity]
    why = "their EXIF says the flash fired" if config.camera_light == "auto" else "refine.camera_light=on"
    log(
        f"refine [{variant}]: {lit} of {len(inputs.views)} training photos lit by a flash ({why}): learned a flash "
        f"at the camera beside the light (RGB {', '.join(f'{x:.3g}' for x in intensity)}), saved with the asset "
        "for scoring its photos; relighting leaves it out (--set refine.camera_light=off: no flash)"
    )
    record["camera_light"] = {"lit_views": lit, "intensity": intensity, "reference_distance": flash.reference_distance}
    return record
