"""The whole method as stages over one run directory: predict -> geometry -> lift -> refine.

Each stage is skipped when its artifact exists and was made with the same settings (and from the
same upstream artifacts); `timings.json` records the seconds each stage took (the paper's Table 3).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from matspray.device import configure_threads, resolve_device
from matspray.data import Scene, load_scene
from matspray.errors import ConfigError
from matspray.lift import LiftConfig, LiftResult, lift
from matspray.refine import VARIANTS, RefineConfig, refine
from matspray.render.visibility import VisibilityConfig
from matspray.rundir import RunDir, fingerprint, timed, to_plain

PRESETS = ("test", "demo", "paper")


@dataclass
class PipelineConfig:
    preset: str = "demo"
    predictor: str = "simulated"
    predictor_options: dict = field(default_factory=dict)  # PredictorOptions fields
    downscale: float = 1.0
    seed: int = 0
    refine_seed: int | None = None  # the refinement's own seed (view order, merger init); None: `seed`
    device: str = "auto"
    geometry: object = None  # GeometryConfig of the preset
    lift: LiftConfig = field(default_factory=LiftConfig)
    visibility: VisibilityConfig | None = field(default_factory=VisibilityConfig)  # None: no shadowing (the paper's shading)
    refine: RefineConfig = field(default_factory=RefineConfig)


def preset_config(preset: str, **overrides) -> PipelineConfig:
    """The settings of a preset (DESIGN.md): `test` for CI, `demo` for 2 CPU cores, `paper` for a GPU."""
    from matspray.geometry.config import preset as geometry_preset

    if preset not in PRESETS:
        raise ConfigError(f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")
    if preset == "test":
        config = PipelineConfig(preset=preset, lift=LiftConfig(samples_per_side=2), visibility=VisibilityConfig(rows=4, resolution=48),
                                refine=RefineConfig(iterations=30, envmap_height=8, light_warmup=10))
    elif preset == "demo":
        config = PipelineConfig(preset=preset, lift=LiftConfig(samples_per_side=4), refine=RefineConfig(iterations=600, envmap_height=16, light_warmup=200))
    else:
        config = PipelineConfig(preset=preset, lift=LiftConfig(samples_per_side=16), visibility=VisibilityConfig(rows=16, resolution=512),
                                refine=RefineConfig(iterations=10000, envmap_height=32, light_warmup=1000))
    config = replace(config, **overrides)
    config.geometry = geometry_preset(preset, seed=config.seed)
    return config


def variant_refine_config(config: PipelineConfig, variant: str) -> RefineConfig:
    """The refinement settings of one variant: the run's, with the variant and the refinement seed
    (`refine_seed`, else the run's `seed`)."""
    if variant not in VARIANTS:
        raise ConfigError(f"unknown variant '{variant}'; choose one of {', '.join(VARIANTS)}")
    seed = config.seed if config.refine_seed is None else config.refine_seed
    return replace(config.refine, variant=variant, seed=seed)


def dataset_identity(scene: Scene) -> dict:
    return {
        "source": str(Path(scene.source).resolve()) if scene.source else None,
        "format": scene.format,
        "train_views": [v.name for v in scene.train],
        "test_views": [v.name for v in scene.test],
        "resolution": [scene.train[0].width, scene.train[0].height],
    }


def asset_stage(variant: str) -> str:
    """Folder of a variant's asset: `asset/` for the full method, `asset-{variant}/` for ablations."""
    return "asset" if variant == "full" else f"asset-{variant}"


class Pipeline:
    """One run directory and the stages that fill it. Every stage method returns its artifact."""

    def __init__(self, data, out, config: PipelineConfig, overwrite: bool = False, progress: bool = True, log=print):
        self.config = config
        self.device = resolve_device(config.device)
        configure_threads(self.device)
        self.scene = load_scene(data, downscale=config.downscale)
        self.run = RunDir(out)
        self.run.claim(dataset_identity(self.scene), overwrite=overwrite)
        self.run.write_config(config)
        self.progress = progress
        self.log = log
        self.dataset_fp = fingerprint(dataset_identity(self.scene), config.downscale)

    # ---------------------------------------------------------------- predict
    def predict_fingerprint(self) -> str:
        return fingerprint("predict", self.dataset_fp, self.config.predictor, self.config.predictor_options)

    def predict(self):
        from matspray.predictors import PredictorOptions, make_predictor, predict_views, read_materials2d, write_materials2d

        fp = self.predict_fingerprint()
        if not self.run.stage_done("materials2d", fp, ["predictor.json"]):
            self.log(f"predict: {self.config.predictor} on {len(self.scene.train)} training views")
            with timed() as t:
                predictor = make_predictor(self.config.predictor, PredictorOptions(**self.config.predictor_options), notify=self.log)
                maps = predict_views(self.scene.train, predictor, notify=self.log)
                write_materials2d(self.run.root, maps, predictor.describe())
            self.run.finish_stage("materials2d", fp, {"predictor": self.config.predictor, **self.config.predictor_options}, t.seconds)
        else:
            self.log("predict: done before, reusing materials2d/")
        return read_materials2d(self.run.root, self.scene.train)

    # ---------------------------------------------------------------- geometry
    def geometry_fingerprint(self) -> str:
        return fingerprint("geometry", self.dataset_fp, self.config.geometry)

    def geometry(self):
        """Trained Gaussians [N] and their oriented normals [N, 3]."""
        from matspray.geometry.ply import read_ply
        from matspray.geometry.train import train_geometry

        fp = self.geometry_fingerprint()
        if not self.run.stage_done("geometry", fp, ["gaussians.ply"]):
            self.log(f"geometry: 3D Gaussian Splatting ({self.config.geometry.iterations} iterations)")
            with timed() as t:
                train_geometry(self.scene, self.config.geometry, self.run.path("geometry"), progress=self.progress)
            self.run.finish_stage("geometry", fp, self.config.geometry, t.seconds)
        else:
            self.log("geometry: done before, reusing geometry/gaussians.ply")
        gaussians, normals = read_ply(self.run.path("geometry", "gaussians.ply"))
        return gaussians.to(self.device), torch.nn.functional.normalize(normals, dim=-1).to(self.device)

    # ---------------------------------------------------------------- lift
    def lift_fingerprint(self) -> str:
        return fingerprint("lift", self.config.lift, self.predict_fingerprint(), self.geometry_fingerprint())

    def lift(self, gaussians, normals, maps) -> LiftResult:
        fp = self.lift_fingerprint()
        path = self.run.path("lift", "projected.pt")
        if not self.run.stage_done("lift", fp, ["projected.pt"]):
            views = self.scene.train
            materials = [maps_to_tensor(maps[v.name]).to(self.device) for v in views]
            with timed() as t:
                result = lift(gaussians, [v.camera.to(self.device) for v in views], materials,
                              [None if v.alpha is None else v.alpha.to(self.device) for v in views], [v.name for v in views],
                              self.config.lift, progress=self.progress)
                save_lift(result, path)
            self.run.finish_stage("lift", fp, self.config.lift, t.seconds, {"stats": result.stats})
            self.log(f"lift: kept {result.stats['gaussians_kept']} of {result.stats['gaussians_in']} Gaussians")
        else:
            self.log("lift: done before, reusing lift/projected.pt")
        return load_lift(path, self.device)

    # ---------------------------------------------------------------- visibility
    def visibility_fingerprint(self) -> str:
        return fingerprint("visibility", self.config.visibility, self.lift_fingerprint())

    def visibility(self, kept) -> torch.Tensor | None:
        """Directional visibility [N, D] of the lifted Gaussians `kept`, or None when shadowing is off."""
        from matspray.data.images import save_torch_atomic
        from matspray.render.visibility import bake_visibility

        if self.config.visibility is None:
            return None
        fp = self.visibility_fingerprint()
        path = self.run.path("visibility", "visibility.pt")
        if not self.run.stage_done("visibility", fp, ["visibility.pt"]):
            self.log(f"visibility: shadow maps of {len(kept)} Gaussians towards {2 * self.config.visibility.rows ** 2} directions")
            with timed() as t:
                save_torch_atomic(bake_visibility(kept, self.config.visibility, progress=self.progress).cpu(), path)
            self.run.finish_stage("visibility", fp, self.config.visibility, t.seconds)
        else:
            self.log("visibility: done before, reusing visibility/visibility.pt")
        values = torch.load(path, map_location=self.device)
        if values.shape[0] != len(kept):
            raise ConfigError(f"{path}: visibility of {values.shape[0]} Gaussians, but the lifted geometry has {len(kept)}; delete the file to bake it again")
        return values

    # ---------------------------------------------------------------- refine
    def refine(self, variant: str = "full"):
        from matspray.asset import read_asset, write_asset

        config = variant_refine_config(self.config, variant)
        stage = asset_stage(variant)
        fp = fingerprint("refine", config, self.lift_fingerprint(), self.visibility_fingerprint() if self.config.visibility else None)
        if self.run.stage_done(stage, fp, ["asset.ply"]):
            self.log(f"refine [{variant}]: done before, reusing {stage}/")
            return read_asset(self.run.path(stage), device=self.device)
        maps = self.predict()
        gaussians, normals = self.geometry()
        lifted = self.lift(gaussians, normals, maps)
        kept = gaussians.subset(lifted.kept)
        views = [v.to(self.device) for v in self.scene.train]
        targets = [maps_to_tensor(maps[v.name]).to(self.device) for v in views]
        visibility = self.visibility(kept)
        with timed() as t:
            result = refine(kept, normals[lifted.kept], lifted.values, lifted.seen, views, targets, self.scene.bounds.to(self.device), config,
                            progress=self.progress, visibility=visibility)
            write_asset(self.run.path(stage), kept, result)
        self.run.finish_stage(stage, fp, config, t.seconds, {"history": result.history})
        return read_asset(self.run.path(stage), device=self.device)

    def run_all(self, variants=("full",)) -> dict:
        return {variant: self.refine(variant) for variant in variants}


def maps_to_tensor(maps) -> torch.Tensor:  # MaterialMaps -> [H, W, 5]
    return torch.cat([maps.basecolor, maps.roughness[..., None], maps.metallic[..., None]], dim=-1)


def save_lift(result: LiftResult, path: Path) -> None:
    from matspray.data.images import save_torch_atomic

    save_torch_atomic({"values": result.values.cpu(), "seen": result.seen.cpu(), "kept": result.kept.cpu(), "view_names": result.view_names,
                       "stats": to_plain(result.stats), "hits": None if result.hits is None else result.hits.cpu()}, path)


def load_lift(path: Path, device) -> LiftResult:
    data = torch.load(path, map_location=device, weights_only=False)
    return LiftResult(values=data["values"], seen=data["seen"], kept=data["kept"], view_names=data["view_names"], stats=data["stats"],
                      hits=data.get("hits"))
