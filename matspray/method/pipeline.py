"""The whole method as stages over one run directory: predict -> geometry -> lift -> refine.
A capture without masks runs geometry first, then `masks` (the object region and every view's mask,
matspray.geometry.region), then predict on the masked views; only the Gaussians in the region are lifted.

Each stage is skipped when its artifact exists and was made with the same settings (and from the
same upstream artifacts); `timings.json` records the seconds each stage took (the paper's Table 3).
The method (`paper` or `matspray`) is part of the fingerprints of the stages it changes (lift,
visibility, refine), so a run folder resumed with the other method recomputes those and reuses the rest.
"""

from __future__ import annotations

import weakref
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.data.crop import CROP_FILE
from matspray.data.images import save_torch_atomic
from matspray.data.scene import dataset_identity
from matspray.data.triangulate import POINTS_FILE, needs_points, points_stage
from matspray.device import configure_threads, out_of_memory_as_error, resolve_device
from matspray.errors import RunError, file_error
from matspray.geometry.config import GeometryConfig
from matspray.geometry.ply import read_ply
from matspray.geometry.region import ObjectRegion
from matspray.geometry.train import prepare_views, train_geometry
from matspray.method.asset import Asset, read_asset, write_asset
from matspray.method.config import PipelineConfig, variant_refine_config
from matspray.method.crop import crop_stage
from matspray.method.estimate import Work, feature_sizes, run_work, view_pixels
from matspray.method.lift import LiftResult, lift, load_lift, save_lift
from matspray.method.masks import ObjectMasks, compute_object_masks, read_object_masks, read_region, write_object_masks
from matspray.method.merger import mlp_dtype
from matspray.method.refine.loop import RefineConfig, RefineInputs, frozen_views, refine
from matspray.predictors import (
    NO_PREDICTOR,
    PredictorOptions,
    make_predictor,
    maps_to_tensor,
    options_for_dataset,
    predict_views,
    predicted_normal_maps,
    read_materials2d,
    read_predictor_info,
    resolve_predictor,
    without_normals,
    write_materials2d,
)
from matspray.presets import WORKING_SIZE, asset_stage, get_variant, variants_for_maps
from matspray.render.backend import RenderUse, rendering_with, resolve_backend
from matspray.render.numba.backend import compile_in_background
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.visibility import bake_visibility
from matspray.rundir import RunDir, fingerprint, timed


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


class Pipeline:
    """One run directory and the stages that fill it. Every stage method returns its artifact."""

    def __init__(
        self,
        data,
        out,
        config: PipelineConfig,
        overwrite: bool = False,
        progress: bool = True,
        log=print,
        wait: bool = False,
    ):
        self.config = config
        self.device = resolve_device(config.device)
        configure_threads(self.device)
        # "torch" or "gsplat"; fails here, before any work. Every stage renders with it (see _working)
        self.backend = resolve_backend(config.backend, self.device, notify=log)
        if self.backend == "numba":  # its kernels compile (a fresh install) or load while the data is read
            compile_in_background()
        # photos larger than the preset's working size are brought to it, unless the config names a downscale
        self.scene = load_scene(data, downscale=config.downscale, max_size=WORKING_SIZE[config.preset])
        if config.downscale is None:
            if self.scene.downscale > 1.0:
                shown = self.scene.train[0]
                original = f"{round(shown.width * self.scene.downscale)}x{round(shown.height * self.scene.downscale)}"
                log(
                    f"photos: {original} brought to {shown.width}x{shown.height}, the {config.preset} preset's "
                    "working size (--downscale 1 keeps them as they are)"
                )
            config = self.config = replace(config, downscale=self.scene.downscale)
        # `auto` becomes a predictor here, and one that cannot serve these views fails here, before any training
        predictor = resolve_predictor(config.predictor, self.scene.train, notify=log)
        if predictor != config.predictor:
            config = self.config = replace(config, predictor=predictor)
        self._predictor_options = options_for_dataset(
            config.predictor, PredictorOptions(**config.predictor_options), self.scene.source
        )
        # a missing or unreadable light probe fails here, before the run folder is touched; it is read once, and the
        # refinement's fingerprint names the file as it was read
        self.probe_identity = self.light_probe_identity()
        self.probe = self.light_probe()  # EnvironmentMap | None
        self.run = RunDir(out)
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
        self.progress = progress
        self.log = log
        self.dataset_fp = fingerprint(dataset_identity(self.scene), config.downscale)
        self.unmasked = not self.scene.has_masks  # masks then come from the geometry (stage `masks`)
        # such a capture without points of its own gets them triangulated at its cameras (stage `points`)
        self.points_fp = (
            fingerprint("points", self.dataset_fp, config.points) if needs_points(self.scene, config.points) else None
        )
        self.has_maps = config.predictor != NO_PREDICTOR  # without 2D maps only the variants that need none run
        self._object_masks: ObjectMasks | None = None
        self._refine_inputs: RefineInputs | None = None  # the upstream stages' artifacts, once read
        self._frozen_views: FrozenViews | None = None  # their blending weights, shared by the variants refined
        self._warmed_lights: dict = {}  # light warm-ups, shared by variants that start alike (refine.warm_up_key)
        self._cropped, self._crop_region = False, None  # whether crop() has run, and the region it cut around
        self._normals_given: bool | None = None  # whether the 2D maps have normal maps, once they are predicted

    def close(self) -> None:
        """Lets the run folder go (see __init__); the pipeline must not write after this."""
        self._release()

    def __enter__(self) -> "Pipeline":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextmanager
    def _working(self, stage: str):
        """One stage's work: timed, rendered with the run's backend, and out of memory said in one line.
        Yields (timer, RenderUse)."""
        with timed() as timer, rendering_with(self.backend) as use, out_of_memory_as_error(stage, self.device):
            yield timer, use

    def _ran(self, use: RenderUse) -> dict:
        """What a stage's record says it ran on: the device, the run's backend and what each render call really used."""
        return {"device": str(self.device), "backend": self.backend, "renders": use.used()}

    def done(self, stage: str, fp: str) -> bool:
        """Whether `stage` (a key of STAGES, or an asset stage) finished with the fingerprint `fp`."""
        where = stage_files(stage)
        return self.run.stage_done(where.folder, fp, list(where.files))

    def _stage(self, stage: str, fp: str, work, before=None, label: str = "") -> bool:
        """How every stage runs, written once. Done before (`done`): said in one line, and nothing runs. Otherwise
        `before()` (what it needs from other stages, outside its timer) and then `work(prepared)` -> (settings,
        record), timed, with the run's backend and out of memory said in one line; its record (settings, seconds, what
        it ran on) is written last, so an interrupted stage is never taken for a finished one. `label` names the stage
        in lines (default `stage`). Returns whether it ran."""
        label, where = label or stage, stage_files(stage)
        if self.done(stage, fp):
            self.log(f"{label}: done before, reusing {where.shown}")
            return False
        prepared = before() if before is not None else None
        with self._working(label) as (timer, use):
            settings, record = work(prepared)
        self.run.finish_stage(where.folder, fp, settings, timer.seconds, {**record, **self._ran(use)})
        return True

    # ---------------------------------------------------------------- predict
    def predictor_options(self) -> PredictorOptions:
        """The configured options; a simulated predictor given no seed takes the synth object's."""
        return self._predictor_options

    def predict_fingerprint(self) -> str:
        masks = () if not self.unmasked else (self.masks_fingerprint(),)  # the predictor sees the masked views
        seed = self.predictor_options().seed  # an object's own seed changes the draws, except 0 (the default draws)
        derived = () if seed in (self.config.predictor_options.get("seed"), None, 0) else ({"object_seed": seed},)
        return fingerprint(
            "predict", self.dataset_fp, self.config.predictor, self.config.predictor_options, *masks, *derived
        )

    def predict(self):
        """The 2D maps of the training views {name: MaterialMaps}; None in a run without a predictor."""
        self.object_masks()
        if not self.has_maps:
            return None
        fp = self.predict_fingerprint()
        self._stage("predict", fp, self._predict)
        return read_materials2d(self.run.root, self.scene.train)

    def _predict(self, _) -> tuple[dict, dict]:
        self.log(f"predict: {self.config.predictor} on {len(self.scene.train)} training views")
        options = self.predictor_options()
        predictor = make_predictor(self.config.predictor, options, notify=self.log)
        write_materials2d(
            self.run.root, predict_views(self.scene.train, predictor, notify=self.log), predictor.describe()
        )
        used = {k: v for k, v in vars(options).items() if v is not None}  # the configured options and a derived seed
        return {"predictor": self.config.predictor, **used}, {}

    # ---------------------------------------------------------------- geometry
    def geometry_fingerprint(self) -> str:
        # trained on predicted normals or split on the maps' edges, the geometry depends on the predictions too
        config = self.geometry_config()
        on_maps = config.predicted_normal_weight > 0 or config.material_edge_threshold > 0
        upstream = [self.predict_fingerprint()] if on_maps else []
        upstream += [self.points_fp] if self.points_fp else []  # none for masked scenes: their fingerprint is kept
        crop = self.crop_fingerprint()
        upstream += [crop] if crop else []
        return fingerprint("geometry", self.dataset_fp, config.identity(), *upstream)

    # ---------------------------------------------------------------- crop (captures without masks)
    def crop_fingerprint(self) -> str | None:
        """None where the photos are never cut: scenes with masks, and the crop switched off (their fingerprints are
        kept)."""
        if not self.unmasked or not self.config.crop.enabled:
            return None
        return fingerprint("crop", self.config.crop, self.config.object_bounds, self.points_fp or self.dataset_fp)

    def crop(self) -> ObjectRegion | None:
        """Cut every photo to its object (matspray.data.crop) before the stages that read them: the windows are found
        once (stage `crop`, from the sparse points) and the scene is read again through them. Returns the region the
        windows were found in (the geometry focuses on it), None when the photos are used whole."""
        fp = self.crop_fingerprint()
        if fp is None:
            return None
        if self._cropped:
            return self._crop_region
        if self.points_fp and not self.done("crop", fp):
            points_stage(self.run, self.points_fp, self.scene, self.config.points, self.progress, self.log)
        self.scene, self._crop_region = crop_stage(
            self.run, fp, self.scene, self.config.crop, self.config.object_bounds, self.log
        )
        self._cropped = True
        return self._crop_region

    def predicted_normals(self) -> bool | None:
        """Whether the 2D maps carry normal maps; None until predicted (then kept: their fingerprint is fixed)."""
        if self._normals_given is not None:
            return self._normals_given
        if not self.has_maps:
            self._normals_given = False
        elif self.done("predict", self.predict_fingerprint()):
            self._normals_given = "normal_space" in read_predictor_info(self.run.root)  # recorded when normal files are
        return self._normals_given

    def maps_have_normals(self) -> bool:
        """`predicted_normals`, predicting the maps first where they are not yet."""
        if self.predicted_normals() is None:
            self.predict()
        return bool(self.predicted_normals())

    def geometry_config(self) -> GeometryConfig:
        """The geometry settings as they apply to this dataset: the object focus only to a capture without masks, the
        predicted normals only where the 2D maps have them (predicted first), the material edges where there are maps,
        and neither to a capture without masks, whose masks, which the predictor sees, come from the geometry."""
        config = self.config.geometry.for_scene(masked=not self.unmasked)
        if config.predicted_normal_weight > 0 and (self.unmasked or not self.maps_have_normals()):
            config = replace(config, predicted_normal_weight=0.0)
        if config.material_edge_threshold > 0 and (self.unmasked or not self.has_maps):
            config = replace(config, material_edge_threshold=0.0)
        return config

    def geometry_normal_targets(self, maps: dict | None = None) -> list[torch.Tensor] | None:
        """The predicted normal maps geometry trains on (world space, per training view), None when it trains on
        none (said in one line where its weight asks for them). `maps`: the 2D maps when the caller has them."""
        if self.geometry_config().predicted_normal_weight <= 0:
            if self.config.geometry.predicted_normal_weight > 0 and self.has_maps and not self.unmasked:
                self.log(without_normals(self.run.path("materials2d"), "geometry"))
            return None
        views = [v.to(self.device) for v in self.scene.train]
        return predicted_normal_maps({n: m.to(self.device) for n, m in (maps or self.predict()).items()}, views)

    def geometry(self):
        """Trained Gaussians [N] and their oriented normals [N, 3]."""
        focus_region = self.crop()  # the photos are cut to the object first (a capture without masks)
        config = self.geometry_config()
        edges = config.material_edge_threshold > 0

        def inputs():  # the predictions (read once for both uses) and the points, outside the geometry's timer
            self.log(f"geometry: 3D Gaussian Splatting ({self.config.geometry.iterations} iterations)")
            maps = self.predict() if edges or config.predicted_normal_weight > 0 else None
            normal_targets = self.geometry_normal_targets(maps)
            if self.points_fp and self.scene.points is None:  # (the crop may have read them already)
                points_stage(self.run, self.points_fp, self.scene, self.config.points, self.progress, self.log)
            return maps, normal_targets

        def train(prepared) -> tuple:
            maps, normal_targets = prepared
            train_geometry(
                self.scene,
                config,
                self.run.path("geometry"),
                device=self.device,
                progress=self.progress,
                normal_targets=normal_targets,
                material_maps=[maps_to_tensor(maps[v.name]) for v in self.scene.train] if edges else None,
                object_bounds=self.config.object_bounds,
                focus_region=focus_region,
            )
            return config, {}

        self._stage("geometry", self.geometry_fingerprint(), train, before=inputs)
        gaussians, normals = read_ply(self.run.path("geometry", "gaussians.ply"))
        return gaussians.to(self.device), torch.nn.functional.normalize(normals, dim=-1).to(self.device)

    # ---------------------------------------------------------------- object masks (captures without masks)
    def masks_fingerprint(self) -> str:
        return fingerprint("masks", self.config.object_bounds, self.geometry_fingerprint())

    def object_masks(self) -> ObjectMasks | None:
        """A capture without masks: the object region, which Gaussians it holds, and every view's mask (their
        rendered alpha), which from here on is the views' alpha. None when the dataset has masks."""
        if not self.unmasked:
            return None
        if self._object_masks is None:
            self.crop()  # the masks belong to the cut photos: cut them first, also when the masks are reused

            def masks_of(gaussians) -> tuple[dict, dict]:
                focused = read_region(self.run.path("geometry"))  # None: the geometry did not focus
                masks = compute_object_masks(
                    gaussians, self.scene, self.config.object_bounds, progress=self.progress, region=focused
                )
                write_object_masks(self.run.path("masks"), masks)
                record = {"region": masks.region.to_json(), "inside": int(masks.inside.sum())}
                return {"object_bounds": self.config.object_bounds}, record

            self._stage("masks", self.masks_fingerprint(), masks_of, before=lambda: self.geometry()[0])
            self._object_masks = read_object_masks(self.run.path("masks"))
            self.log(
                f"masks: the object is {int(self._object_masks.inside.sum())} of "
                f"{len(self._object_masks.inside)} Gaussians, "
                f"inside the {self._object_masks.region.describe()}"
            )
            self._object_masks.apply(self.scene)
        return self._object_masks

    def object_geometry(self):
        """The Gaussians [N] and normals [N, 3] of the object: all of them, or those in a capture's object region."""
        gaussians, normals = self.geometry()
        masks = self.object_masks()
        if masks is None:
            return gaussians, normals
        inside = masks.inside.to(gaussians.means.device)
        return gaussians.subset(inside), normals[inside]

    # ---------------------------------------------------------------- lift
    def lift_config(self):
        """The lift's settings. A run without 2D maps lifts only to learn which Gaussians the views see (no value is
        read), so one ray per pixel does: a sixteenth of the demo preset's rays
        (the skull capture: about 9 min less)."""
        return self.config.lift if self.has_maps else replace(self.config.lift, samples_per_side=1)

    def lift_views(self) -> list:
        """The views lifted from: the training views; without 2D maps, at the size Gaussian Splatting trained at
        (`geometry.resolution`), which is where it decided what each view shows (a quarter of the rays at the demo
        preset)."""
        return self.scene.train if self.has_maps else prepare_views(self.scene.train, self.config.geometry.resolution)

    def lift_pixel_share(self) -> float:
        """The lifted views' pixels over the training views' (1 with 2D maps; see `lift_views`)."""
        if self.has_maps:
            return 1.0
        sizes = [(v.width, v.height) for v in self.scene.train]
        return sum(view_pixels(w, h, self.config.geometry.resolution) for w, h in sizes) / sum(w * h for w, h in sizes)

    def lift_fingerprint(self) -> str:
        at = () if self.has_maps else ({"views_at": self.config.geometry.resolution},)
        return fingerprint(
            "lift", self.config.method, self.lift_config(), self.predict_fingerprint(), self.geometry_fingerprint(), *at
        )

    def lift(self, gaussians, maps) -> LiftResult:
        """Lift the 2D maps onto the Gaussians. Without maps (None) lifting still decides, from the same rays and
        masks, which Gaussians the views see (the kept ones); its values are zeros that no variant reads."""
        path = self.run.path("lift", "projected.pt")

        def views_and_maps() -> tuple[list, list]:  # the lifted views and their 2D maps [H, W, 5] (zeros without)
            views = self.lift_views()
            if maps is None:
                return views, [torch.zeros(v.height, v.width, 5, device=self.device) for v in views]
            return views, [maps_to_tensor(maps[v.name]).to(self.device) for v in views]

        def lifted(prepared) -> tuple:
            views, values = prepared
            cameras = [v.camera.to(self.device) for v in views]
            alphas = [None if v.alpha is None else v.alpha.to(self.device) for v in views]
            config = self.lift_config()
            result = lift(gaussians, cameras, values, alphas, [v.name for v in views], config, progress=self.progress)
            save_lift(result, path)
            self.log(f"lift: kept {result.stats['gaussians_kept']} of {result.stats['gaussians_in']} Gaussians")
            return config, {"stats": result.stats}

        self._stage("lift", self.lift_fingerprint(), lifted, before=views_and_maps)
        return load_lift(path, self.device)

    # ---------------------------------------------------------------- visibility
    def visibility_fingerprint(self) -> str | None:
        if self.config.visibility is None:
            return None
        return fingerprint("visibility", self.config.visibility, self.lift_fingerprint())

    def visibility(self, kept) -> torch.Tensor | None:
        """Directional visibility [N, D] of the lifted Gaussians `kept`, or None when shadowing is off."""
        if self.config.visibility is None:
            return None
        path = self.run.path("visibility", "visibility.pt")

        def bake(_) -> tuple:
            directions = 2 * self.config.visibility.rows**2
            self.log(f"visibility: shadow maps of {len(kept)} Gaussians towards {directions} directions")
            save_torch_atomic(bake_visibility(kept, self.config.visibility, progress=self.progress).cpu(), path)
            return self.config.visibility, {}

        self._stage("visibility", self.visibility_fingerprint(), bake)
        values = torch.load(path, map_location=self.device)
        if values.shape[0] != len(kept):
            raise RunError(
                f"{path}: visibility of {values.shape[0]} Gaussians, but the lifted geometry has {len(kept)}; "
                "delete the file to bake it again"
            )
        return values

    # ---------------------------------------------------------------- refine
    def refine_inputs(self) -> RefineInputs:
        """Predict, geometry, lift and visibility (each reused when done): what refinement reads. Read
        once per Pipeline: the variants of one run share them."""
        if self._refine_inputs is None:
            self._refine_inputs = self._read_refine_inputs()
        return self._refine_inputs

    def _read_refine_inputs(self) -> RefineInputs:
        maps = self.predict() if self.has_maps else None
        gaussians, normals = self.object_geometry()
        lifted = self.lift(gaussians, maps)
        kept = gaussians.subset(lifted.kept)
        views = [v.to(self.device) for v in self.scene.train]
        normal_maps = (
            predicted_normal_maps({n: m.to(self.device) for n, m in maps.items()}, views) if maps is not None else None
        )
        if normal_maps is None and self.config.refine.predicted_normal_weight > 0 and maps is not None:
            self.log(without_normals(self.run.path("materials2d"), "refinement"))
        return RefineInputs(
            gaussians=kept,
            normals=normals[lifted.kept],
            values=lifted.values,
            seen=lifted.seen,
            views=views,
            targets=[maps_to_tensor(maps[v.name]).to(self.device) for v in views] if maps is not None else [],
            bounds=self.scene.bounds.to(self.device),
            visibility=self.visibility(kept),
            normal_maps=normal_maps,
        )

    def light_probe(self) -> EnvironmentMap | None:
        """The known training light (`light_probe`), at the size of the light refinement would learn;
        None when unset."""
        if self.config.light_probe is None:
            return None
        return EnvironmentMap.from_file(self.config.light_probe, height=self.config.refine.envmap_height)

    def light_probe_identity(self) -> tuple:
        """What the refinement's fingerprint adds for a light probe: its path, size and time (nothing when unset, so
        runs without one keep their fingerprints)."""
        if self.config.light_probe is None:
            return ()
        path = Path(self.config.light_probe)
        if not path.is_file():
            raise file_error(
                path,
                "the light probe (--set light_probe=PATH) does not exist",
                "give an HDR lat-long map (.exr or .hdr)",
            )
        stat = path.stat()
        return ({"light_probe": str(path.resolve()), "bytes": stat.st_size, "modified_ns": stat.st_mtime_ns},)

    def merger_dtype(self, config: RefineConfig) -> torch.dtype:
        """What the merger of a refinement with `config` multiplies in on this run's device (`precision` resolved)."""
        return mlp_dtype(config.merger.precision, self.device)

    def refine_fingerprint(self, variant: str) -> str:
        learns_light = (
            self.probe is not None and get_variant(variant).learns_light
        )  # variants without a light ignore the probe
        config = self.refine_config(variant)
        return fingerprint(
            "refine",
            self.config.method,
            config,
            str(self.merger_dtype(config)),  # what "auto" is on this machine
            self.lift_fingerprint(),
            self.visibility_fingerprint(),
            *(self.probe_identity if learns_light else ()),
        )

    def refine_config(self, variant: str) -> RefineConfig:
        """The refinement settings of `variant` in this run: the predicted normals only in a variant that reads the 2D
        maps, and only where they have normal maps."""
        config = variant_refine_config(self.config, variant)
        if not (get_variant(variant).uses_maps and config.predicted_normal_weight > 0 and self.maps_have_normals()):
            config = replace(config, predicted_normal_weight=0.0)
        return config

    def refine(self, variant: str = "full") -> Asset:
        variants_for_maps([variant], self.has_maps)  # a variant that reads 2D maps is refused in a run without them
        config = self.refine_config(variant)
        stage = asset_stage(variant)
        probe = self.probe if get_variant(variant).learns_light else None  # variants without a light ignore it

        def refined(inputs) -> tuple:
            if self._frozen_views is None and get_variant(variant).trains and config.iterations > 0:
                self._frozen_views = frozen_views(inputs)
            frozen, warmed = self._frozen_views, self._warmed_lights
            result = refine(inputs, config, self.progress, light=probe, frozen=frozen, warmed_lights=warmed)
            write_asset(self.run.path(stage), inputs.gaussians, result)
            precision = str(self.merger_dtype(config)).removeprefix("torch.")
            return config, {"history": result.history, "frozen_views": result.frozen, "merger_precision": precision}

        fp = self.refine_fingerprint(variant)
        self._stage(stage, fp, refined, before=self.refine_inputs, label=f"refine [{variant}]")
        return read_asset(self.run.path(stage), device=self.device)

    def work(self, variants=None) -> Work:
        """What `run_all(variants)` has left to do, for `estimate.estimate_line`."""
        names = variants_for_maps(variants, self.has_maps)
        # predictions not made yet (the estimate must not make them): no refinement is done, nor a geometry that
        # follows their normals
        pending = self.predicted_normals() is None
        geometry_waits = pending and self.config.geometry.predicted_normal_weight > 0 and not self.unmasked
        stages = {"points": self.points_fp} if self.points_fp else {}
        if not geometry_waits:
            stages |= {"geometry": self.geometry_fingerprint(), "masks": self.masks_fingerprint()}
            stages["lift"] = self.lift_fingerprint()
        done = frozenset(stage for stage, fp in stages.items() if self.done(stage, fp))
        to_refine = [v for v in names if pending or not self.done(asset_stage(v), self.refine_fingerprint(v))]
        return run_work(
            [(v.width, v.height) for v in self.scene.train],
            self.config.geometry.iterations,
            self.config.geometry.resolution,
            self.lift_config().samples_per_side ** 2 * self.lift_pixel_share(),
            [(variant_refine_config(self.config, v).iterations, get_variant(v).uses_maps) for v in to_refine],
            self.unmasked,
            done,
            self.feature_views(),
        )

    def feature_views(self) -> list[tuple[int, int]]:
        """The sizes of the photos the `points` stage extracts features from (none when the run has no such stage):
        the photos as loaded, before the working size, at most `points.max_size` on their long side."""
        if not self.points_fp:
            return []
        views = [(v.width, v.height) for v in self.scene.train]
        return feature_sizes(views, self.scene.downscale, self.config.points.max_size)

    def run_all(self, variants=None) -> dict:
        """Refine `variants` (default: full, or in a run without 2D maps the variants that need none)."""
        return {variant: self.refine(variant) for variant in variants_for_maps(variants, self.has_maps)}
