"""A run's settings: one frozen `PipelineConfig`, the presets (sizes) and the methods, as data.

A config is built in three layers, each a plain mapping of settings:
  1. the preset: image and model sizes (`test` for CI, `demo` for 2 CPU cores, `paper` for one GPU), each a partial
     config (`presets.PRESET_SETTINGS`) over the dataclasses' defaults, which are the demo preset;
  2. the method: `matspray` (default) is the preset as is; `paper` switches every addition of ours
     off, leaving the paper's text (and its released code where the text is silent);
  3. overrides, by dotted setting name (`lift.min_support`, `refine.iterations`, ...).

Every addition of `matspray` over `paper` is one row of `ADDITIONS`: the setting it changes, the
paper's value and its source, so each can be measured on its own (`without=` switches single additions off).

Each setting is declared once, on its field (`matspray.settings.setting`: default, help, flag). This module imports
no torch: the command line reads PipelineConfig's fields for its options' help; the stages' sections are imported
when a config is first made.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import TYPE_CHECKING

from matspray.errors import ConfigError, SettingError
from matspray.presets import (
    ADDITION_NAMES,
    ADDITIONS,
    METHODS,
    PRESET_SETTINGS,
    PRESETS,
    SHADOW_MAPS,
    VARIANT_OWNED_SETTINGS,
    get_variant,
)
from matspray.rundir import fingerprint, to_plain
from matspray.settings import setting

if TYPE_CHECKING:
    from matspray.data.crop import CropConfig
    from matspray.data.triangulate import PointsConfig
    from matspray.geometry.config import GeometryConfig
    from matspray.method.lift import LiftConfig
    from matspray.method.refine.loop import RefineConfig
    from matspray.render.shade.visibility import VisibilityConfig

_QUALITY = PRESET_SETTINGS["quality"]  # its sizes, as `--preset`'s help names them
QUALITY_SIZES = (
    f"{_QUALITY['geometry']['resolution']} px, up to "
    + f"{_QUALITY['geometry']['max_gaussians']:,}".replace(",", " ")
    + f" Gaussians and {_QUALITY['refine']['iterations']} refinement steps"
)

# where each section's dataclass lives ("module:Class"), imported when a config is first made
SECTIONS = {
    "points": "matspray.data.triangulate:PointsConfig",
    "crop": "matspray.data.crop:CropConfig",
    "geometry": "matspray.geometry.config:GeometryConfig",
    "lift": "matspray.method.lift:LiftConfig",
    "visibility": "matspray.render.shade.visibility:VisibilityConfig",
    "refine": "matspray.method.refine.loop:RefineConfig",
}


def section_class(name: str) -> type:
    """The dataclass of the section `name` of PipelineConfig (imports its stage)."""
    module, _, cls = SECTIONS[name].partition(":")
    return getattr(importlib.import_module(module), cls)


def section_types() -> dict[str, type]:
    """The sections' dataclasses by class name: what PipelineConfig's annotations name (`typing.get_type_hints`)."""
    return {section_class(name).__name__: section_class(name) for name in SECTIONS}


def _section(name: str, **settings):
    """A factory of the section `name`, with `settings` over its defaults."""
    return lambda: section_class(name)(**settings)


def unknown_preset(preset: str) -> SettingError:
    return SettingError("preset", f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")


# The 2D model's normals, in every preset under `matspray` (the paper trains Gaussian Splatting on DiffusionRenderer's
# normals of highly specular objects only, and refines normals by the rendering loss: `--method paper` turns both off,
# rows `geometry-normals` and `refine-normals` of `presets.ADDITIONS`): Gaussian Splatting trains on them and
# refinement keeps its normals near them, at this weight. A run applies them where its 2D maps have normal maps and
# turns them off elsewhere (`plan.resolve_plan`); the stages' own settings default to 0 (off), for the stages called
# alone.
NORMAL_PRIOR_WEIGHT = 1.0


@dataclass(frozen=True)
class PipelineConfig:
    preset: str = setting(
        "demo",
        "sizes: test (tiny, for CI), demo (128 px, 2 CPU cores), "
        f"quality ({QUALITY_SIZES}: sharper, slower, more memory; the README's first "
        "table says how long it took), paper (512 px, one GPU)",
        flag="--preset",
    )
    method: str = setting(
        "matspray",
        "matspray: the paper plus our measured additions; paper: exactly the paper's method (and its released code "
        "where the text is silent)",
        flag="--method",
    )
    predictor: str = setting(
        "simulated", "the 2D model of the material maps, as a spec (`matspray.predictors`)", flag="--predictor"
    )
    predictor_options: dict = setting(factory=dict, help="the predictor's options (PredictorOptions)", flag="--weights")
    downscale: float | None = setting(
        None,
        "shrink images by this factor on load (default: photos whose long side exceeds the preset's working size, "
        "test 128 / demo 256 / paper 800 px, are brought to it; 1 keeps them)",
        flag="--downscale",
    )
    seed: int = setting(0, "random seed of the run (geometry, predictor draws, refinement unless refine_seed)")
    refine_seed: int | None = setting(None, "the refinement's own seed (view order, merger init); None: `seed`")
    device: str = setting("auto", "auto (CUDA when available; default), cpu, cuda or cuda:N", flag="--device")
    backend: str = setting(
        "auto",
        "rasterizer: auto (default; on CUDA gsplat when its CUDA code builds, else torch; on the CPU numba), torch "
        "(the readable reference), numba (compiled, CPU only) or gsplat (CUDA only; pip install 'matspray[cuda]')",
        flag="--backend",
    )
    points: PointsConfig = setting(factory=_section("points"), help="the initial points of a capture that brings none")
    crop: CropConfig = setting(factory=_section("crop"), help="a capture without masks: each photo cut to its object")
    geometry: GeometryConfig = setting(
        factory=_section("geometry", predicted_normal_weight=NORMAL_PRIOR_WEIGHT), help="Gaussian Splatting"
    )
    lift: LiftConfig = setting(factory=_section("lift"), help="the 2D maps lifted onto the Gaussians")
    visibility: VisibilityConfig | None = setting(
        None,
        "bake each Gaussian's visibility and shadow the PBR shading with it (off: the paper's unshadowed split-sum "
        "shading)",
        flag="--set shadows",
    )
    refine: RefineConfig = setting(
        factory=_section("refine", predicted_normal_weight=NORMAL_PRIOR_WEIGHT),
        help="refinement: the Neural Merger and the light",
    )
    object_bounds: tuple[float, ...] | None = setting(
        None,
        "captures without masks: the object region, 'x,y,z,r' (a sphere) or 'x0,y0,z0,x1,y1,z1' (a box) in world "
        "units (default: chosen automatically after geometry; see docs/data.md, captures without masks)",
        flag="--object-bounds",
    )
    light_probe: str | None = setting(
        None,
        "a known training light (an HDR lat-long map of the capture's light, world frame): the PBR variants shade "
        "with it instead of estimating one; None: estimate it (the paper)",
    )

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise unknown_preset(self.preset)
        if self.method not in METHODS:
            raise SettingError("method", f"unknown method '{self.method}'; choose one of {', '.join(METHODS)}")
        from matspray.geometry.region import given_region
        from matspray.render.backend import BACKENDS

        if self.backend not in BACKENDS:
            raise SettingError("backend", f"unknown backend '{self.backend}'; choose one of {', '.join(BACKENDS)}")
        if self.downscale is not None and not self.downscale > 0:
            raise SettingError("downscale", f"must be > 0, got {self.downscale}")
        if self.object_bounds is not None:
            object.__setattr__(self, "object_bounds", tuple(float(v) for v in self.object_bounds))
            given_region(self.object_bounds)  # raises SettingError("object_bounds", ...) when malformed


# ------------------------------------------------------------------------------------------ presets (matspray.presets)
def shadow_maps(preset: str) -> VisibilityConfig:
    """The shadow maps of `preset`, for a run with baked shadows (off by default; docs/defaults.md says why). Where
    they are switched on (`visibility=shadow_maps(preset)`, `--set shadows=on`), they have the preset's size."""
    if preset not in SHADOW_MAPS:
        raise unknown_preset(preset)
    return section_class("visibility")(**SHADOW_MAPS[preset])


def preset_paths(partial: dict, prefix: str = "") -> dict:
    """A preset's partial config {section: {setting: value}} as {dotted setting: value}."""
    paths = {}
    for name, value in partial.items():
        if isinstance(value, dict):
            paths |= preset_paths(value, f"{prefix}{name}.")
        else:
            paths[prefix + name] = value
    return paths


def preset_settings(preset: str) -> dict:
    """`PRESET_SETTINGS[preset]` as {dotted setting: value}, checked against the fields: a name that is no setting,
    or a value of another type than the field's default, fails here (in every config made, so in every test)."""
    defaults = PipelineConfig()
    paths = preset_paths(PRESET_SETTINGS[preset])
    for path, value in paths.items():
        section, _, name = path.rpartition(".")
        target = defaults
        for part in section.split(".") if section else ():
            target = getattr(target, part, None)
        known = {f.name: f for f in fields(target)} if is_dataclass(target) else {}
        if name not in known:
            raise ConfigError(f"presets.PRESET_SETTINGS[{preset!r}]: {path} is no setting")
        default = known[name].default
        if type(default) in (bool, int, str) and type(value) is not type(default):
            raise ConfigError(
                f"presets.PRESET_SETTINGS[{preset!r}]: {path} = {value!r} is not a {type(default).__name__}"
            )
    return paths


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
    from matspray.geometry.config import preset as geometry_preset

    presets = preset_settings(preset)  # its geometry part is GeometryConfig's preset (`geometry_preset`)
    try:
        geometry = geometry_preset(preset, seed=seed, **geometry_settings)
    except SettingError as exc:
        raise SettingError(f"geometry.{exc.setting}", exc.problem) from None
    except ConfigError as exc:
        raise SettingError("geometry", str(exc)) from None
    config = PipelineConfig(preset=preset, method=method, geometry=geometry)
    stages = {path: value for path, value in presets.items() if not path.startswith("geometry.")}
    for path, value in {**stages, **settings}.items():
        config = with_setting(config, path, value)
    return config


def variant_refine_config(config: PipelineConfig, variant: str) -> RefineConfig:
    """The refinement settings of one variant: the run's, with the variant and the refinement seed
    (`refine_seed`, else the run's `seed`); a variant without the 2D maps' loss weighs the photometric loss 1, as
    `refine.photo_weight` weighs it against that loss; a setting only some variants read (`VARIANT_OWNED_SETTINGS`)
    is recorded as that table says for the others."""
    kind = get_variant(variant)
    seed = config.seed if config.refine_seed is None else config.refine_seed
    photo_weight = config.refine.photo_weight if kind.uses_maps else 1.0
    refine = replace(config.refine, variant=variant, seed=seed, photo_weight=photo_weight)
    for path, (reads, others) in VARIANT_OWNED_SETTINGS.items():
        if not reads(kind):
            refine = with_setting(refine, path, setting_default(refine, path) if others is None else others)
    return refine


def setting_default(config, path: str):
    """The declared default of the dotted setting `path` of `config` (a frozen dataclass of settings)."""
    head, _, rest = path.partition(".")
    return setting_default(getattr(config, head), rest) if rest else getattr(type(config)(), head)


def default_settings(preset: str, method: str = "matspray") -> dict:
    """Every default setting of `preset` and `method` as plain values, less what names one run (predictor, seeds)."""
    config = build_config(preset, method)
    return to_plain(replace(config, predictor="", predictor_options={}, seed=0, refine_seed=None))


def defaults_fingerprint(preset: str, method: str = "matspray") -> str:
    """The fingerprint of `default_settings`: a results file records it, so a published figure is tied to the
    defaults it was measured with."""
    return fingerprint(default_settings(preset, method))
