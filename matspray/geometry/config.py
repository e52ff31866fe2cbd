"""Settings of geometry training; the presets (test, demo, paper) change them (matspray.presets)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

from matspray.errors import ConfigError, SettingError, check_unit_interval
from matspray.presets import GEOMETRY
from matspray.settings import setting


@dataclass(frozen=True)
class GeometryConfig:
    preset: str = setting("demo", "the preset whose sizes these are (follows --preset)", internal=True)
    seed: int = setting(0, "random seed of the initial points and the training (follows the run's seed)", internal=True)
    resolution: int = setting(128, "longest image side used for training (views are downscaled to it); 0: as loaded")
    iterations: int = setting(3000, "Gaussian Splatting steps (the preset's; the densification schedule follows)")

    init_points: int = setting(
        8000,
        "initialisation: the sparse points of a COLMAP scene, points on the masks' visual hull, or random "
        "points in the object bounds; isotropic, init_scale times the spacing of their neighbours",
    )
    init: str = setting(
        "hull",
        'a scene with masks and no points starts from: "hull", points on the masks\' visual hull; "random", '
        "points drawn uniformly in the object bounds (the paper's unit cube)",
    )
    init_opacity: float = setting(0.3, "opacity of the initial Gaussians")
    init_scale: float = setting(0.7, "initial size, in multiples of the spacing of the neighbouring points")
    sh_degree: int = setting(3, "highest spherical-harmonics degree of the colours")
    sh_degree_every: int = setting(500, "raise the active SH degree by one every this many iterations")

    # learning rates (3DGS)
    lr_means: float = setting(
        1.6e-4, "learning rate of the positions, scaled by the scene extent; decays exponentially to lr_means_final"
    )
    lr_means_final: float = setting(
        1.6e-6,
        "learning rate of the positions at the last step (exponential decay from lr_means)",
    )
    lr_sh_dc: float = setting(2.5e-3, "learning rate of the colours' constant term")
    lr_sh_rest: float = setting(2.5e-3 / 20, "learning rate of the colours' higher SH terms")
    lr_opacity: float = setting(0.05, "learning rate of the opacities")
    lr_scales: float = setting(5e-3, "learning rate of the (log) scales")
    lr_quats: float = setting(1e-3, "learning rate of the rotations")

    # adaptive density control (3DGS)
    densify_from: int = setting(200, "first step of densification")
    densify_until: int = setting(2000, "last step of densification")
    densify_every: int = setting(100, "steps between densifications")
    opacity_reset_every: int = setting(1000, "steps between opacity resets")
    grad_threshold: float = setting(2e-4, "mean screen-space gradient (NDC units) that triggers clone / split")
    absgrad: bool = setting(
        False,
        "densify on the summed |per-pixel gradient| of each projected centre instead of |summed gradient| "
        "(AbsGS, as gsplat's strategy offers it); gradients of opposite sign then no longer cancel, so it "
        "wants a larger grad_threshold (gsplat: 8e-4)",
    )
    percent_dense: float = setting(0.01, "clone below, split above this fraction of the scene extent")
    prune_opacity: float = setting(0.005, "Gaussians less opaque than this are pruned")
    max_screen_fraction: float = setting(0.15, "prune Gaussians wider than this fraction of the image (after a reset)")
    max_world_fraction: float = setting(0.1, "prune Gaussians larger than this fraction of the scene extent")
    max_gaussians: int = setting(
        40000,
        "cap on the Gaussians densification may grow to (lower it when a GPU runs out of memory)",
    )
    material_edge_threshold: float = setting(
        0.0,
        "split Gaussians whose footprint straddles an edge of the 2D material maps (a change of base colour, "
        "roughness or metallic of at least this much in it, averaged over the views that see it; "
        "matspray.geometry.material_edges), so that one Gaussian does not carry two materials into the lift; "
        "0: off. Needs the run's 2D maps",
    )

    # losses
    ssim_weight: float = setting(0.2, "L = (1 - w) L1 + w (1 - SSIM) on sRGB values")
    alpha_weight: float = setting(0.5, "L1 between rendered and true alpha (data with masks)")
    flatten_weight: float = setting(0.05, "mean ratio of the shortest to the middle axis of each Gaussian")
    normal_weight: float = setting(0.05, "1 - cos between rendered normals and normals of the rendered depth")
    normal_from: float = setting(0.3, "fraction of the iterations after which the normal loss is on")
    random_background: bool = setting(True, "composite on a random colour each step (data with masks)")
    predicted_normal_weight: float = setting(
        0.0,
        "1 - |cos| between the 2D predictor's normal maps (world space) and the rendered normals (every step)"
        " and the normals of the rendered depth (after `normal_from`), over the object: the paper's treatment"
        ' of specular objects ("we train Gaussian Splatting on DiffusionRenderer normals"); 0: off (a run\'s '
        "default is `config.NORMAL_PRIOR_WEIGHT`, where its 2D maps have normal maps)",
    )

    focus_from: float = setting(
        0.15,
        "object focus, for captures without masks (a scene with masks trains on its object alone): after this"
        " fraction of the iterations (at that densification step; 0: never) the object region is found on the"
        " Gaussians so far (matspray.geometry.region's rule, or the run's object_bounds), and from then on "
        "only its Gaussians grow",
    )
    focus_grad_scale: float = setting(
        0.5,
        "after the focus, the object's Gaussians are densified at this times grad_threshold",
    )
    background_budget: float = setting(
        0.2,
        "at the focus the background keeps at most this times max_gaussians of its Gaussians (those covering "
        "most); it is no longer opacity-reset or pruned for its size and draws the room coarsely: the budget "
        "goes to the object",
    )

    checkpoint_every: int = setting(500, "steps between checkpoints (a rerun resumes from the last)")

    def __post_init__(self) -> None:
        positive = [
            "iterations",
            "init_points",
            "densify_every",
            "opacity_reset_every",
            "max_gaussians",
            "checkpoint_every",
            "sh_degree_every",
        ]
        for name in positive:
            if getattr(self, name) < 1:
                raise SettingError(name, f"must be >= 1, got {getattr(self, name)}")
        if self.init not in INITS:
            raise SettingError("init", f"unknown start '{self.init}'; choose one of {', '.join(INITS)}")
        if not 0 <= self.sh_degree <= 3:
            raise SettingError("sh_degree", f"must be 0..3, got {self.sh_degree}")
        if self.resolution < 0:
            raise SettingError("resolution", f"must be >= 0 (0 keeps the images' size), got {self.resolution}")
        if self.predicted_normal_weight < 0:
            raise SettingError("predicted_normal_weight", f"must be >= 0, got {self.predicted_normal_weight}")
        if self.focus_grad_scale <= 0:
            raise SettingError("focus_grad_scale", f"must be > 0, got {self.focus_grad_scale}")
        check_unit_interval(
            self,
            "ssim_weight",
            "normal_from",
            "init_opacity",
            "focus_from",
            "background_budget",
            "material_edge_threshold",
        )

    def to_dict(self) -> dict:
        return asdict(self)

    def identity(self) -> dict:
        """The settings that name a trained geometry (fingerprints, checkpoints): `to_dict` without the settings added
        after runs existed while they hold the value that keeps training as it was, so those runs stay valid."""
        return {k: v for k, v in asdict(self).items() if ADDED_LATER.get(k, object()) != v}

    def for_scene(self, masked: bool) -> "GeometryConfig":
        """The settings as they apply to a scene with (`masked`) or without masks: a masked scene trains on its object
        alone, so the object focus settings do not apply and take the values that leave them out of `identity`."""
        return replace(self, **{k: ADDED_LATER[k] for k in FOCUS}) if masked else self


INITS = ("hull", "random")

# settings added after geometry runs existed -> the value under which training is what it was before them
ADDED_LATER = {
    "init": "hull",
    "predicted_normal_weight": 0.0,
    "focus_from": 0.0,
    "focus_grad_scale": 1.0,
    "background_budget": 1.0,
    "material_edge_threshold": 0.0,
}
FOCUS = ("focus_from", "focus_grad_scale", "background_budget")  # the object focus settings (captures without masks)


GEOMETRY_PRESETS = {name: GeometryConfig(preset=name, **changes) for name, changes in GEOMETRY.items()}


# iteration counts that follow `iterations` when only that is overridden
SCHEDULE = (
    "densify_from",
    "densify_until",
    "densify_every",
    "opacity_reset_every",
    "sh_degree_every",
    "checkpoint_every",
)


def preset(name: str, **overrides) -> GeometryConfig:
    """The named preset with some settings replaced. Overriding `iterations` alone stretches the
    schedule (densification window, opacity resets, SH degree steps, checkpoints) to match."""
    if name not in GEOMETRY_PRESETS:
        raise ConfigError(f"unknown geometry preset {name!r}; choose one of {', '.join(GEOMETRY_PRESETS)}")
    known = {f.name for f in fields(GeometryConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ConfigError(f"geometry config: unknown settings {', '.join(unknown)}")
    base = GEOMETRY_PRESETS[name]
    if "iterations" in overrides and overrides["iterations"] >= 1:
        ratio = overrides["iterations"] / base.iterations
        for key in SCHEDULE:
            overrides.setdefault(key, max(1, round(getattr(base, key) * ratio)))
    return replace(base, **overrides)
