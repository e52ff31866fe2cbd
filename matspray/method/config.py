"""A run's settings: one frozen `PipelineConfig`, the presets (sizes) and the methods, as data.

A config is built in three layers, each a plain mapping of settings:
  1. the preset: image and model sizes (`test` for CI, `demo` for 2 CPU cores, `paper` for one GPU);
  2. the method: `matspray` (default) is the preset as is; `paper` switches every addition of ours
     off, leaving the paper's text (and its released code where the text is silent);
  3. overrides, by dotted setting name (`lift.min_support`, `refine.iterations`, ...).

Every addition of `matspray` over `paper` is one row of `ADDITIONS`: the setting it changes, the
paper's value and its source, so each can be measured on its own (`without=` switches single additions off).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass, replace

from matspray.data.crop import CropConfig
from matspray.data.triangulate import PointsConfig
from matspray.errors import ConfigError, SettingError
from matspray.geometry.config import GeometryConfig
from matspray.geometry.config import preset as geometry_preset
from matspray.geometry.region import given_region
from matspray.method.lift import LiftConfig
from matspray.method.refine.loop import RefineConfig
from matspray.presets import ADDITION_NAMES, ADDITIONS, METHODS, PRESETS, STAGE_SETTINGS, get_variant
from matspray.presets import SHADOW_MAPS as SHADOW_MAP_SIZES
from matspray.render.backend import BACKENDS
from matspray.render.shade.visibility import VisibilityConfig
from matspray.rundir import fingerprint, to_plain


def unknown_preset(preset: str) -> SettingError:
    return SettingError("preset", f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")


# The 2D model's normals, in every preset under `matspray` (the paper trains Gaussian Splatting on DiffusionRenderer's
# normals of highly specular objects only, and refines normals by the rendering loss: `--method paper` turns both off,
# rows `geometry-normals` and `refine-normals` of `presets.ADDITIONS`): Gaussian Splatting trains on them and
# refinement keeps its normals near them, at this weight. A run applies them where its 2D maps have normal maps and
# turns them off elsewhere (`Pipeline.geometry_config`, `Pipeline.refine_config`); the stages' own settings default to
# 0 (off), for the stages called alone.
NORMAL_PRIOR_WEIGHT = 1.0


@dataclass(frozen=True)
class PipelineConfig:
    preset: str = "demo"
    method: str = "matspray"
    predictor: str = "simulated"
    predictor_options: dict = field(default_factory=dict)  # PredictorOptions fields
    # shrink images by this on load; None: bring photos larger than the preset's working size to it
    downscale: float | None = None
    seed: int = 0
    refine_seed: int | None = None  # the refinement's own seed (view order, merger init); None: `seed`
    device: str = "auto"
    # rasterizer: auto (gsplat when CUDA and gsplat are present, numba on the CPU), torch, numba or gsplat
    backend: str = "auto"
    points: PointsConfig = field(default_factory=PointsConfig)  # the initial points of a capture that brings none
    crop: CropConfig = field(default_factory=CropConfig)  # a capture without masks: each photo cut to its object
    geometry: GeometryConfig = field(
        default_factory=lambda: GeometryConfig(predicted_normal_weight=NORMAL_PRIOR_WEIGHT)
    )
    lift: LiftConfig = field(default_factory=LiftConfig)
    # None: no shadowing (the paper's, and our default); `shadow_maps(preset)` turns it on
    visibility: VisibilityConfig | None = None
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(predicted_normal_weight=NORMAL_PRIOR_WEIGHT))
    # captures without masks: the object region (4: sphere, 6: box); None: automatic
    object_bounds: tuple[float, ...] | None = None
    # a known training light (an HDR lat-long map of the capture's light, world frame): the PBR variants shade with it
    # instead of estimating one; None: estimate it (the paper)
    light_probe: str | None = None

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise unknown_preset(self.preset)
        if self.method not in METHODS:
            raise SettingError("method", f"unknown method '{self.method}'; choose one of {', '.join(METHODS)}")
        if self.backend not in BACKENDS:
            raise SettingError("backend", f"unknown backend '{self.backend}'; choose one of {', '.join(BACKENDS)}")
        if self.downscale is not None and not self.downscale > 0:
            raise SettingError("downscale", f"must be > 0, got {self.downscale}")
        if self.object_bounds is not None:
            object.__setattr__(self, "object_bounds", tuple(float(v) for v in self.object_bounds))
            given_region(self.object_bounds)  # raises SettingError("object_bounds", ...) when malformed


# ------------------------------------------------------------------------------------------ presets (matspray.presets)
# Baked shadows are off by default (docs/defaults.md says why). Where they are switched on
# (`visibility=shadow_maps(preset)`, `--shadows on`), their shadow maps have the preset's size.
SHADOW_MAPS: dict[str, VisibilityConfig] = {name: VisibilityConfig(**sizes) for name, sizes in SHADOW_MAP_SIZES.items()}


def shadow_maps(preset: str) -> VisibilityConfig:
    """The shadow maps of `preset`, for a run with baked shadows."""
    if preset not in SHADOW_MAPS:
        raise unknown_preset(preset)
    return SHADOW_MAPS[preset]


# ------------------------------------------------------------------------------------------ methods
def method_settings(method: str, without: tuple[str, ...] = ()) -> dict:
    """The settings a method changes: none for `matspray` (less the additions named in `without`), every
    addition's paper value for `paper`."""
    if method not in METHODS:
        raise SettingError("method", f"unknown method '{method}'; choose one of {', '.join(METHODS)}")
    unknown = sorted(set(without) - set(ADDITION_NAMES))
    if unknown:
        raise SettingError(
            "without", f"unknown addition(s) {', '.join(unknown)}; choose from {', '.join(ADDITION_NAMES)}"
        )
    if method == "paper" and without:
        raise SettingError("without", "turns off additions of --method matspray; --method paper has none to turn off")
    off = ADDITION_NAMES if method == "paper" else without
    return {a.setting: a.paper for a in ADDITIONS if a.name in off}


# ------------------------------------------------------------------------------------------ building
def with_setting(config, path: str, value):
    """`config` (a frozen dataclass) with the dotted setting `path` replaced; a bad value raises a
    SettingError naming the setting by its full dotted path (relative to `config`)."""
    head, _, rest = path.partition(".")
    names = {f.name for f in fields(config)}
    if head not in names:
        raise SettingError(path, f"no such setting (known here: {', '.join(sorted(names))})")
    if rest:
        inner = getattr(config, head)
        if not is_dataclass(inner):
            raise SettingError(path, f"'{head}' is off or has no setting '{rest}'")
        try:
            value = with_setting(inner, rest, value)
        except SettingError as exc:
            raise SettingError(f"{head}.{exc.setting}", exc.problem) from None
    try:
        return replace(config, **{head: value})
    except SettingError:
        raise
    except (ConfigError, TypeError, ValueError) as exc:
        raise SettingError(head, str(exc)) from None


def build_config(
    preset: str = "demo", method: str = "matspray", without: tuple[str, ...] = (), **settings
) -> PipelineConfig:
    """The config of `preset` and `method`, with `settings` by dotted name (pass them as a dict:
    `build_config("demo", **{"lift.min_support": 0.3})`; top-level ones as keywords, e.g. `seed=1`).
    Geometry follows the preset; `seed` seeds it too, and `geometry.iterations` alone stretches its schedule."""
    if preset not in PRESETS:
        raise unknown_preset(preset)
    seed = settings.get("seed", 0)
    turned_off = method_settings(method, tuple(without))
    clash = sorted(set(turned_off) & set(settings)) if without else []
    if clash:
        names = ", ".join(a.name for a in ADDITIONS if a.setting in clash)
        raise SettingError(clash[0], f"--without {names} sets it too (to {turned_off[clash[0]]}); give one of the two")
    # the method's values first, the settings given over them (an override of a paper value is the user's to make)
    settings = {"geometry.predicted_normal_weight": NORMAL_PRIOR_WEIGHT, **turned_off, **settings}
    geometry_settings = {k.split(".", 1)[1]: settings.pop(k) for k in list(settings) if k.startswith("geometry.")}
    try:
        geometry = geometry_preset(preset, seed=seed, **geometry_settings)
    except SettingError as exc:
        raise SettingError(f"geometry.{exc.setting}", exc.problem) from None
    except ConfigError as exc:
        raise SettingError("geometry", str(exc)) from None
    config = PipelineConfig(preset=preset, method=method, geometry=geometry)
    for path, value in {**STAGE_SETTINGS[preset], **settings}.items():
        config = with_setting(config, path, value)
    return config


def variant_refine_config(config: PipelineConfig, variant: str) -> RefineConfig:
    """The refinement settings of one variant: the run's, with the variant and the refinement seed
    (`refine_seed`, else the run's `seed`); a variant without the 2D maps' loss weighs the photometric loss 1, as
    `refine.photo_weight` weighs it against that loss."""
    kind = get_variant(variant)
    seed = config.seed if config.refine_seed is None else config.refine_seed
    photo_weight = config.refine.photo_weight if kind.uses_maps else 1.0
    return replace(config.refine, variant=variant, seed=seed, photo_weight=photo_weight)


def default_settings(preset: str, method: str = "matspray") -> dict:
    """Every default setting of `preset` and `method` as plain values, less what names one run (predictor, seeds)."""
    config = build_config(preset, method)
    return to_plain(replace(config, predictor="", predictor_options={}, seed=0, refine_seed=None))


def defaults_fingerprint(preset: str, method: str = "matspray") -> str:
    """The fingerprint of `default_settings`: a results file records it, so a published figure is tied to the
    defaults it was measured with."""
    return fingerprint(default_settings(preset, method))
