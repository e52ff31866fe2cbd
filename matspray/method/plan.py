"""What a run will compute, before it computes it: the data it reads at the preset's working size, each stage's
settings as they apply to that data, and each stage's fingerprint (its settings and its upstream stages' fingerprints).
A stage whose files exist with the same fingerprint is done and reused (`RunPlan.done`); `Pipeline` (the stages
themselves) is a `RunPlan`.

The method (`paper` or `matspray`) is part of the fingerprints of the stages it changes (lift, visibility, refine), so
a run folder resumed with the other method recomputes those and reuses the rest.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
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
from matspray.method.merger import mlp_dtype
from matspray.method.refine.loop import RefineConfig
from matspray.predictors import (
    NO_PREDICTOR,
    PredictorOptions,
    options_for_dataset,
    read_predictor_info,
    resolve_predictor,
)
from matspray.presets import WORKING_SIZE, asset_stage, get_variant, variants_for_maps
from matspray.render.shade.envmap import EnvironmentMap
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


class RunPlan(ABC):
    """The resolved config of one run over one scene, and what follows from it: each stage's settings and
    fingerprint, and which stages are done. The 2D maps' normals are known only once predicted, so `predict`
    (the stage) is the one thing a plan needs from the stages."""

    def __init__(self, config: PipelineConfig, scene: Scene, device: torch.device, run: RunDir):
        self.config, self.scene, self.device, self.run = config, scene, device, run
        self.predictor_options = options_for_dataset(
            config.predictor, PredictorOptions(**config.predictor_options), scene.source
        )
        # a missing or unreadable light probe fails here; it is read once, and the refinement's fingerprint names the
        # file as it was read
        self.probe_identity = light_probe_identity(config.light_probe)
        self.probe = (
            None
            if config.light_probe is None
            else EnvironmentMap.from_file(config.light_probe, height=config.refine.envmap_height)
        )
        self.dataset_fp = fingerprint(dataset_identity(scene), config.downscale)
        self.unmasked = not scene.has_masks  # masks then come from the geometry (stage `masks`)
        # such a capture without points of its own gets them triangulated at its cameras (stage `points`)
        self.points_fp = (
            fingerprint("points", self.dataset_fp, config.points) if needs_points(scene, config.points) else None
        )
        self.has_maps = config.predictor != NO_PREDICTOR  # without 2D maps only the variants that need none run
        self._normals_given: bool | None = None  # whether the 2D maps have normal maps, once they are predicted

    @abstractmethod
    def predict(self):
        """The predict stage: the 2D maps {view name: MaterialMaps}, predicted where they are not yet."""

    def done(self, stage: str, fp: str) -> bool:
        """Whether `stage` (a key of STAGES, or an asset stage) finished with the fingerprint `fp`."""
        where = stage_files(stage)
        return self.run.stage_done(where.folder, fp, list(where.files))

    def predicted_normals(self) -> bool | None:
        """Whether the 2D maps carry normal maps; None until predicted (then kept: their fingerprint is fixed)."""
        if self._normals_given is None:
            if not self.has_maps:
                self._normals_given = False
            elif self.done("predict", self.predict_fingerprint()):
                self._normals_given = "normal_space" in read_predictor_info(self.run.root)  # recorded with the files
        return self._normals_given

    def maps_have_normals(self) -> bool:
        """`predicted_normals`, predicting the maps first where they are not yet."""
        if self.predicted_normals() is None:
            self.predict()
        return bool(self.predicted_normals())

    def predict_fingerprint(self) -> str:
        masks = () if not self.unmasked else (self.masks_fingerprint(),)  # the predictor sees the masked views
        seed = self.predictor_options.seed  # an object's own seed changes the draws, except 0 (the default draws)
        derived = () if seed in (self.config.predictor_options.get("seed"), None, 0) else ({"object_seed": seed},)
        options = self.config.predictor_options
        return fingerprint("predict", self.dataset_fp, self.config.predictor, options, *masks, *derived)

    def crop_fingerprint(self) -> str | None:
        """None where the photos are never cut: scenes with masks, and the crop switched off (their fingerprints are
        kept)."""
        if not self.unmasked or not self.config.crop.enabled:
            return None
        return fingerprint("crop", self.config.crop, self.config.object_bounds, self.points_fp or self.dataset_fp)

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

    def geometry_fingerprint(self) -> str:
        # trained on predicted normals or split on the maps' edges, the geometry depends on the predictions too
        config = self.geometry_config()
        on_maps = config.predicted_normal_weight > 0 or config.material_edge_threshold > 0
        upstream = [self.predict_fingerprint()] if on_maps else []
        upstream += [self.points_fp] if self.points_fp else []  # none for masked scenes: their fingerprint is kept
        crop = self.crop_fingerprint()
        upstream += [crop] if crop else []
        return fingerprint("geometry", self.dataset_fp, config.identity(), *upstream)

    def masks_fingerprint(self) -> str:
        return fingerprint("masks", self.config.object_bounds, self.geometry_fingerprint())

    def lift_config(self):
        """The lift's settings. A run without 2D maps lifts only to learn which Gaussians the views see (no value is
        read), so one ray per pixel does."""
        return self.config.lift if self.has_maps else replace(self.config.lift, samples_per_side=1)

    def lift_views(self) -> list:
        """The views lifted from: the training views; without 2D maps, at the size Gaussian Splatting trained at
        (`geometry.resolution`), which is where it decided what each view shows."""
        return self.scene.train if self.has_maps else prepare_views(self.scene.train, self.config.geometry.resolution)

    def lift_pixel_share(self) -> float:
        """The lifted views' pixels over the training views' (1 with 2D maps; see `lift_views`)."""
        if self.has_maps:
            return 1.0
        sizes = [(v.width, v.height) for v in self.scene.train]
        return sum(view_pixels(w, h, self.config.geometry.resolution) for w, h in sizes) / sum(w * h for w, h in sizes)

    def lift_fingerprint(self) -> str:
        at = () if self.has_maps else ({"views_at": self.config.geometry.resolution},)
        upstream = (self.predict_fingerprint(), self.geometry_fingerprint())
        return fingerprint("lift", self.config.method, self.lift_config(), *upstream, *at)

    def visibility_fingerprint(self) -> str | None:
        if self.config.visibility is None:
            return None
        return fingerprint("visibility", self.config.visibility, self.lift_fingerprint())

    def merger_dtype(self, config: RefineConfig) -> torch.dtype:
        """What the merger of a refinement with `config` multiplies in on this run's device (`precision` resolved)."""
        return mlp_dtype(config.merger.precision, self.device)

    def refine_config(self, variant: str) -> RefineConfig:
        """The refinement settings of `variant` in this run: the predicted normals only in a variant that reads the 2D
        maps, and only where they have normal maps."""
        config = variant_refine_config(self.config, variant)
        if not (get_variant(variant).uses_maps and config.predicted_normal_weight > 0 and self.maps_have_normals()):
            config = replace(config, predicted_normal_weight=0.0)
        return config

    def refine_fingerprint(self, variant: str) -> str:
        config = self.refine_config(variant)
        probe = self.probe_identity if self.probe is not None and get_variant(variant).learns_light else ()
        upstream = (self.lift_fingerprint(), self.visibility_fingerprint())
        # the merger's dtype: what "auto" is on this machine; variants without a light ignore the probe
        return fingerprint("refine", self.config.method, config, str(self.merger_dtype(config)), *upstream, *probe)

    def feature_views(self) -> list[tuple[int, int]]:
        """The sizes of the photos the `points` stage extracts features from (none when the run has no such stage):
        the photos as loaded, before the working size, at most `points.max_size` on their long side."""
        if not self.points_fp:
            return []
        views = [(v.width, v.height) for v in self.scene.train]
        return feature_sizes(views, self.scene.downscale, self.config.points.max_size)

    def work(self, variants=None) -> Work:
        """What refining `variants` has left to do, for `estimate.estimate_line`. Nothing is computed: predictions not
        made yet leave every refinement to do, and the geometry too where it follows their normals."""
        names = variants_for_maps(variants, self.has_maps)
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
