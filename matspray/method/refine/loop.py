"""Refinement (paper section 3.4): Neural Merger + environment map, trained with two losses.

Each step takes a random training view, rasterizes the merged per-Gaussian materials and normals
into a G-buffer, and
  - compares the rasterized material maps with the view's 2D maps by L1 (L_Image; updates the merger
    only); with `basecolor_loss="scale-invariant"` the base colour after the least-squares scale onto
    the 2D map, as the paper's released code does, so a predictor's per-view exposure drift does not
    pull the merger,
  - shades the G-buffer with split-sum image-based lighting from the learnable environment map and
    compares it with the photo by 0.8 L1 + 0.2 (1 - SSIM) (L_3DGS; updates the merger and the map),
    weighted `photo_weight` against the material loss,
  - keeps the environment map smooth: `light_tv_weight` times the total variation of its log radiance
    (`render.latlong.total_variation`; the released code regularises its map by total variation too).
Before that, `light_warmup` steps fit the environment map alone, with the materials the variant starts
from. Variants with the PBR loss also refine each Gaussian's shading normal by it (`matspray.method.refine.normals`;
`normal_lr`, 0 keeps the geometry's), held near the geometry's normal, or a predicted one, by `normal_prior_weight`.
Positions, shapes and opacities are frozen, so each view's blending weights are computed once and reused every
step (and the merger runs only for the Gaussians that cover at least `min_coverage` pixels of the step's view).
With a directional visibility per Gaussian (`RefineInputs.visibility`; only with `--shadows on`, off by
default), the PBR render is shadowed (`render.visibility`), so the photo loss does not push shadows into
the base color.
Two optional settings, off by default (docs/defaults.md):
`basecolor_spread_weight` adds the KL divergence of the base-colour merger's weights from equal weights,
and `align_view_gains` divides each view's base colour by its estimated gain before any variant fuses.

The variants (`matspray.presets`) choose what produces the per-Gaussian materials.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from matspray.data.scene import View
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.material import METALLIC_INDEX
from matspray.method.merger import (
    MergerConfig,
    align_view_gains,
    view_gains,
)
from matspray.method.refine.camera_light import CameraLight, check_mode, lit_views, reference_distance
from matspray.method.refine.metallic import MetallicFitConfig, fit_metallic
from matspray.method.refine.normals import ShadingNormals, normal_prior, smoothed_normals
from matspray.method.refine.sources import MaterialSource, material_source
from matspray.method.refine.steps import adam as adam_optimizer
from matspray.method.refine.steps import check_finite, check_finite_gradients, optimize  # noqa: F401 (the checks: callers' API)
from matspray.method.refine.terms import (  # noqa: F401 (the material losses: callers' API)
    DEFAULT_HUBER_DELTA,
    TermOptions,
    light_images,
    masked_huber,
    masked_l1,
    material_loss,
    prefiltered_light,
    scale_invariant_l1,
    total_loss,
    view_losses,
    view_terms,
    weighted_l1,
)
from matspray.method.refine.training import (  # noqa: F401 (ViewConstants, frozen_views, light_prior: callers' API)
    TrainingViews,
    ViewConstants,
    frozen_views,
    light_prior,
)
from matspray.presets import Variant, get_variant
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.light import Light
from matspray.render.shade.models import LIGHT_MODELS, light_model
from matspray.render.shade.sh import sh_dc_to_rgb
from matspray.settings import setting

BASECOLOR_LOSSES = ("l1", "scale-invariant", "huber")
BASECOLOR_STARTS = ("grey", "photos")


@dataclass(frozen=True)
class RefineConfig:
    iterations: int = setting(600, "refinement steps of each variant (the preset's)")
    merger_lr: float = setting(1e-3, "learning rate of the Neural Merger (the paper: 0.001)")
    envmap_lr: float = setting(3e-2, "learning rate of the estimated light's log radiance")
    supervised_lr: float = setting(
        5e-2,
        "free per-Gaussian logits (3DGS's rate for per-Gaussian opacity logits); at the merger's 1e-3 a "
        "Gaussian seen in half the steps moves its logit by ~0.2 in 400 steps and stays grey",
    )
    envmap_height: int = setting(16, "learnable lat-long map is H x 2H (another light model: its lat-long drawing's)")
    envmap_init: float = setting(0.5, "initial constant radiance")
    light_model: str = setting(
        "latlong",
        'the estimated light\'s model: "latlong" (a lat-long map of envmap_height rows) or "sg" (2 x envmap_height '
        "spherical Gaussians)",
    )
    light_tv_weight: float = setting(
        3e-4,
        "weight of the total variation of the map's log radiance (0: no prior; `benchmarks.light`)",
    )
    camera_light: str = setting(
        "auto",
        'a flash at each photo\'s camera, learned beside the environment (`method.refine.camera_light`): "auto" on the '
        'photos whose EXIF says their flash fired, "on" on every photo, "off" never',
    )
    light_warmup: int = setting(
        200,
        "steps that fit only the environment map to the photos, materials fixed at their start",
    )
    min_coverage: float = setting(
        0.2,
        "per step the Neural Merger runs only for Gaussians covering >= this many pixels of the view; the "
        "others (a sliver of the image) reuse their last value, without gradient (free per-Gaussian materials, "
        "which cost nothing to read, learn for every Gaussian the view shows)",
    )
    material_weight: float = setting(
        1.0, "weight of L_Image, the L1 between the rendered material maps and the 2D maps"
    )
    photo_weight: float = setting(
        2.0,
        "L_3DGS against L_Image, in the variants that read the 2D maps (the others weigh it 1): the paper's "
        "text gives no weight (1), its released code adds the term twice (2)",
    )
    basecolor_loss: str = setting(
        "l1",
        '"l1" (the paper, and our default), "scale-invariant" (only for variants with the PBR loss, which '
        'then sets the brightness; supervised compares by plain L1 then) or "huber" (quadratic below '
        "`basecolor_huber_delta`, so views that differ by a little are averaged, as proj-average does; linear"
        " above, so a wrong view or batch is outvoted, as by L1's median)",
    )
    basecolor_huber_delta: float = setting(
        DEFAULT_HUBER_DELTA,
        'linear base colour; where "huber" turns quadratic to linear',
    )
    photo_l1_weight: float = setting(0.8, "lambda of L_3DGS; (1 - lambda) goes to D-SSIM")
    align_view_gains: bool = setting(
        False,
        "divide each view's base colour (lifted values and 2D map) by its gain against the multi-view average"
        " (`merger.view_gains`): per-view exposure and white balance removed before any variant fuses",
    )
    normal_lr: float = setting(
        1e-3,
        "Adam's rate for the per-Gaussian shading normals (variants with the PBR loss; about the radians a "
        "normal turns per step); 0: shade with the geometry's normals, frozen",
    )
    normal_neighbours: int = setting(
        16,
        "the geometry's normals, each averaged over this many nearest Gaussians (`normals.smoothed_normals`) "
        "before shading and refinement, in every variant; 0: as the geometry trained them (the paper)",
    )
    normal_prior_weight: float = setting(
        0.1,
        "weight of 1 - |cos| between each refined normal and the geometry's: the photo loss alone also turns "
        "normals to fake shading that the materials get wrong",
    )
    predicted_normal_weight: float = setting(
        0.0,
        "weight of 1 - |cos| between the rendered normals and the view's predicted normal map (when the "
        "predictor gives one), per object pixel: the 2D model's normals as a target (a run's default is "
        "`config.NORMAL_PRIOR_WEIGHT`, in the variants that read the 2D maps, where they have normal maps)",
    )
    metallic_quantile: float = setting(
        0.25,
        "the quantile of the views' metallic that the material loss is smallest at (its pinball loss on that "
        'channel; 0.5: L1, the median, as the paper): 2D models "often predict partial metallicity in certain '
        'views" (the paper), which a lower quantile outvotes even where most views have it',
    )
    metallic_prior_weight: float = setting(
        0.01,
        "photos-only variant only: weight of the mean metallic of the Gaussians a step refines (without 2D maps "
        "nothing else tells metal from a dielectric, and the photo loss alone turns a skull into grey metal): an L1 "
        "pull towards a dielectric that only the photos' evidence of metal outweighs (the other variants: 0, so "
        "no-prior stays the paper's baseline)",
    )
    metallic_prior_start: float = setting(
        0.1,
        "photos-only variant only: the metallic its free per-Gaussian materials start from, and its light warm-up "
        "sees (the others: 0.5, an uninformed grey)",
    )
    basecolor_start: str = setting(
        "grey",
        'photos-only variant only: what its free base colour starts from: "grey" (0.5, as the other free variants) '
        "or \"photos\" (each Gaussian's view-independent colour from Gaussian Splatting, the photos' light in it, "
        "for the light and the photo loss to take out)",
    )
    basecolor_spread_weight: float = setting(
        0.0,
        "weight of the base-colour merger's KL divergence from equal weights over the seen views (softmax "
        "variants only): keeps it averaging views unless the losses show some are better",
    )
    variant: str = setting("full", "the variant refined (set per variant by the pipeline)", internal=True)
    seed: int = setting(
        0, "seed of the view order and the merger's start (the run's refine_seed, else its seed)", internal=True
    )
    log_every: int = setting(10, "steps between history records, and between the reads of whether losses stayed finite")
    merger: MergerConfig = setting(factory=MergerConfig, help="the Neural Merger")
    metallic_fit: MetallicFitConfig = setting(
        factory=MetallicFitConfig,
        help="variants with the material loss: after the merger, each Gaussian's metallic fitted to the 2D maps "
        "through the renderer (`matspray.method.refine.metallic`; steps 0: off), which sharpens the metal edges the "
        "lift blurs",
    )

    def __post_init__(self):
        get_variant(self.variant)
        if self.iterations < 0:
            raise SettingError("iterations", f"must be >= 0, got {self.iterations}")
        if self.normal_neighbours < 0:
            raise SettingError("normal_neighbours", f"must be >= 0 (0: off), got {self.normal_neighbours}")
        if self.basecolor_loss not in BASECOLOR_LOSSES:
            raise SettingError(
                "basecolor_loss", f"unknown loss '{self.basecolor_loss}'; choose one of {', '.join(BASECOLOR_LOSSES)}"
            )
        for name in (
            "material_weight",
            "photo_weight",
            "light_tv_weight",
            "min_coverage",
            "light_warmup",
            "basecolor_spread_weight",
            "normal_lr",
            "normal_prior_weight",
            "predicted_normal_weight",
            "metallic_prior_weight",
        ):
            if not getattr(self, name) >= 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")
        if self.basecolor_start not in BASECOLOR_STARTS:
            raise SettingError(
                "basecolor_start",
                f"unknown start '{self.basecolor_start}'; choose one of {', '.join(BASECOLOR_STARTS)}",
            )
        if not 0.0 < self.metallic_prior_start < 1.0:
            raise SettingError("metallic_prior_start", f"must be in (0, 1), got {self.metallic_prior_start}")
        if not 0.0 < self.metallic_quantile < 1.0:
            raise SettingError("metallic_quantile", f"must be in (0, 1), got {self.metallic_quantile}")
        if not self.basecolor_huber_delta > 0:
            raise SettingError("basecolor_huber_delta", f"must be > 0, got {self.basecolor_huber_delta}")
        if self.envmap_height < 2:
            raise SettingError("envmap_height", f"must be >= 2, got {self.envmap_height}")
        check_mode(self.camera_light)
        if self.light_model not in LIGHT_MODELS:
            raise SettingError(
                "light_model", f"unknown model '{self.light_model}'; choose one of {', '.join(LIGHT_MODELS)}"
            )

    @property
    def kind(self) -> Variant:
        return get_variant(self.variant)

    @property
    def refines_normals(self) -> bool:
        """Whether this variant's normals are trained: only the PBR loss sees them."""
        return self.kind.learns_light and self.normal_lr > 0


@dataclass(frozen=True)
class RefineInputs:
    """Everything refinement reads: the lifted Gaussians and the training views they were lifted from."""

    gaussians: Gaussians  # [N] frozen geometry
    normals: Tensor  # [N, 3] unit, any orientation (each view flips them to face it)
    values: Tensor  # [N, V, 5] lifted per-view materials (`matspray.material` layout)
    seen: Tensor  # [N, V] bool: the views that count for each Gaussian
    views: list[View]  # the V training views, in the order of `values`
    targets: list[Tensor]  # V 2D maps [H, W, 5] (base colour linear, roughness, metallic)
    bounds: Tensor  # [2, 3] object box (the merger's positional encoding)
    visibility: Tensor | None = None  # [N, D] directional visibility that shadows the PBR render; None: unshadowed
    normal_maps: list[Tensor] | None = None  # V predicted normal maps [H, W, 3], world space, unit (0: no prediction)
    # `normals` averaged over K neighbours, by K: made once for all the variants refined from these inputs
    smoothed: dict[int, Tensor] = field(default_factory=dict, repr=False, compare=False)

    def normals_over(self, neighbours: int) -> Tensor:  # -> [N, 3] unit
        """The geometry's normals, each averaged over its `neighbours` nearest Gaussians (0: as they are)."""
        if neighbours == 0:
            return self.normals
        if neighbours not in self.smoothed:
            means, opacities = self.gaussians.means.detach(), self.gaussians.opacities.detach()
            self.smoothed[neighbours] = smoothed_normals(self.normals, means, opacities, neighbours)
        return self.smoothed[neighbours]


# ------------------------------------------------------------------------------------------ losses
def spread_loss(weights: Tensor, seen: Tensor) -> Tensor:  # [K, V], [K, V] bool -> []
    """Mean KL divergence of each Gaussian's merger weights from equal weights over its seen views,
    log(n_seen) - H(w): 0 for the plain average, log(n_seen) for a single view."""
    n_seen = seen.sum(-1).clamp_min(1).to(weights.dtype)
    entropy = -(weights * weights.clamp_min(1e-12).log()).sum(-1)
    return (n_seen.log() - entropy).mean()


# ------------------------------------------------------------------------------------------ optimisation
def envmap_group(envmap: Light, config: RefineConfig) -> dict:
    """The environment map's optimizer parameter group."""
    return {"params": list(envmap.parameters()), "lr": config.envmap_lr, "name": "environment map"}


def light_groups(envmap: Light, camera_light: CameraLight | None, config: RefineConfig) -> list[dict]:
    """The estimated lights' parameter groups: the environment's, and a camera light's at the same rate."""
    if camera_light is None:
        return [envmap_group(envmap, config)]
    flash = {"params": list(camera_light.parameters()), "lr": config.envmap_lr, "name": "camera light"}
    return [envmap_group(envmap, config), flash]


def warm_up_light(
    training: TrainingViews,
    materials: Tensor,
    normals: Tensor,
    envmap: Light,
    config: RefineConfig,
    generator,
    progress: bool,
) -> None:
    """Fit the environment map (and the camera light, when the views have one) alone to the photos for
    `config.light_warmup` steps, with fixed materials [N, 5] (what the source starts from: the projection average for
    the merger variants)."""
    camera_light = training.camera_light
    optimizer = adam_optimizer(light_groups(envmap, camera_light, config))

    def photo_losses(index: int):
        terms = view_losses(training, index, materials, normals, envmap, config, False, False, camera_light)
        return terms, total_loss(terms, config)

    optimize(
        optimizer,
        len(training),
        config.light_warmup,
        photo_losses,
        generator,
        "light warm-up",
        progress,
        check_at=lambda step: step % config.log_every == 0,
    )


def warm_up_key(materials: Tensor, config: RefineConfig) -> tuple:
    """What the light warm-up's outcome depends on besides the training views: the materials it holds fixed (their
    bytes' digest) and every setting but those of the material source (variant, merger)."""
    digest = hashlib.sha256(materials.detach().cpu().contiguous().numpy().tobytes()).hexdigest()
    return digest, repr(replace(config, variant="full", merger=MergerConfig()))


@dataclass
class RefineResult:
    materials: Tensor  # [N, 5]
    normals: Tensor  # [N, 3] unoriented unit normals used for shading
    source: MaterialSource
    envmap: Light | None  # None for variants without the PBR loss
    history: list[dict]
    visibility: Tensor | None = None  # [N, D] the shadowing used (kept with the asset for relighting)
    frozen: dict | None = None  # what the frozen views kept (FrozenViews.describe()); None when none were made
    camera_light: CameraLight | None = None  # the flash estimated beside the environment, on photos that had one
    flash_views: int = 0  # how many training views that flash lit


def aligned_inputs(inputs: RefineInputs) -> RefineInputs:
    """`inputs` with each view's base colour, in the lifted values and in its 2D map, divided by the view's gain."""
    gains = view_gains(inputs.values, inputs.seen)  # [V, 3]
    targets = [align_view_gains(target, gain.to(target)) for target, gain in zip(inputs.targets, gains)]
    return replace(inputs, values=align_view_gains(inputs.values, gains), targets=targets)


def starting_source(variant: Variant, inputs: RefineInputs, config: RefineConfig, device) -> MaterialSource:
    """The variant's material source on `device`, at its start: photos-only's a dielectric until the photos say
    otherwise, its base colour grey or the Gaussians' own colours (`basecolor_start`); the others grey."""
    means = inputs.gaussians.means.detach()
    source = material_source(variant, means, inputs.values, inputs.seen, inputs.bounds, config.merger).to(device)
    if variant.dielectric_prior:
        source.start_metallic(config.metallic_prior_start)
        if config.basecolor_start == "photos":
            source.start_base_color(sh_dc_to_rgb(inputs.gaussians.sh[:, 0].detach()))
    return source


def refine(
    inputs: RefineInputs,
    config: RefineConfig,
    progress: bool = True,
    on_checkpoint=None,
    light: Light | None = None,
    frozen: FrozenViews | None = None,
    warmed_lights: dict | None = None,
    graphs: bool = True,
) -> RefineResult:
    """Train the variant's material source (and the environment map) on the training views.
    `on_checkpoint(step, source, envmap, history)`: called every 100 steps and at the end. `light`: a known training
    light (a light probe, a benchmark object's true light) the PBR variants shade with as given: no warm-up, never
    optimised. `frozen`: `frozen_views(inputs)` kept by the caller for several variants. `warmed_lights`: a dict kept
    for the variants of one run, where a light warm-up's outcome is found again by a variant that starts from the
    same materials and settings (`warm_up_or_reuse`). `graphs`: the loss terms and the light's prefiltering as CUDA
    graphs on a CUDA device (`TrainingViews`); False: op by op (the same values)."""
    torch.manual_seed(config.seed)
    variant = config.kind
    gaussians, normals = inputs.gaussians, inputs.normals_over(config.normal_neighbours)
    device = gaussians.device
    if config.align_view_gains:
        inputs = aligned_inputs(inputs)
    source = starting_source(variant, inputs, config, device)
    envmap = starting_light(config, light, device) if variant.learns_light else None
    estimates_light = envmap is not None and light is None
    history: list[dict] = []
    if not source.trainable or config.iterations == 0:
        return RefineResult(source().detach(), normals, source, envmap, history, inputs.visibility)

    camera_light, lit = starting_camera_light(config, inputs, device) if estimates_light else (None, None)
    training = TrainingViews(inputs, frozen, graphs, camera_light, lit)
    source_lr = source.learning_rate(config)
    groups = [{"params": list(source.parameters()), "lr": source_lr, "name": f"{variant.name} materials"}]
    if estimates_light:
        groups.extend(light_groups(envmap, camera_light, config))
    generator = torch.Generator().manual_seed(config.seed)
    with torch.no_grad():
        last_materials = source()  # [N, 5] each Gaussian's latest merged value
    if estimates_light and config.light_warmup > 0:
        warm_up_or_reuse(training, last_materials, normals, envmap, config, generator, progress, warmed_lights)
    shading = ShadingNormals(normals).to(device) if config.refines_normals else None
    if shading is not None:  # after the warm-up, which lights the geometry's normals
        groups.append({"params": list(shading.parameters()), "lr": config.normal_lr, "name": "shading normals"})
    optimizer = adam_optimizer(groups)

    def refine_losses(index: int):
        return step_losses(index, training, source, last_materials, normals, shading, envmap, config)

    def log(step: int, terms: dict, bar) -> None:
        if logs(step):
            with torch.no_grad():
                values = torch.stack(list(terms.values())).tolist() if terms else []  # one host read
            record = {"step": step, **dict(zip(terms, values))}
            history.append(record)
            bar.set_postfix({k: f"{v:.4f}" for k, v in record.items() if k != "step"})
        if checkpoints(step):
            on_checkpoint(step, source, envmap, history)

    def logs(step: int) -> bool:
        return step % config.log_every == 0 or step == config.iterations

    def checkpoints(step: int) -> bool:  # finiteness is read before each: none is written from a diverged state
        return on_checkpoint is not None and (step % 100 == 0 or step == config.iterations)

    name, check_at = f"refine [{variant.name}]", lambda step: logs(step) or checkpoints(step)
    optimize(optimizer, len(training), config.iterations, refine_losses, generator, name, progress, log, check_at)
    with torch.no_grad():
        final_normals = normals if shading is None else shading().detach()
        materials = source().detach()
    if variant.uses_maps and config.metallic_fit.steps > 0:
        materials = with_fitted_metallic(materials, final_normals, envmap, training, inputs.targets, config)
    frozen_used = training.frozen.describe()
    flash = None if camera_light is None else camera_light.fixed()
    return RefineResult(
        materials, final_normals, source, envmap, history, inputs.visibility, frozen_used, flash, sum(training.lit)
    )


def step_losses(
    index: int,
    training: "TrainingViews",
    source: MaterialSource,
    last_materials: Tensor,  # [N, 5] each Gaussian's latest merged value (updated in place for the view's Gaussians)
    normals: Tensor,  # [N, 3] the geometry's
    shading: ShadingNormals | None,
    envmap: Light | None,
    config: RefineConfig,
) -> tuple[dict, Tensor]:
    """One refinement step's loss terms on training view `index` and their weighted total: the material source runs
    only for the Gaussians the view shows."""
    variant = config.kind
    active = training.frozen.contributing_ids(index, source.min_coverage(config))
    spread = config.basecolor_spread_weight > 0 and variant.softmax
    merged, weights = source(active, return_weights=True) if spread else (source(active), {})
    materials = last_materials.index_copy(0, active, merged)
    last_materials.index_copy_(0, active, merged.detach())
    shading_normals = normals if shading is None else shading()
    terms = view_losses(
        training,
        index,
        materials,
        shading_normals,
        envmap,
        config,
        with_material=variant.uses_maps,
        with_normals=shading is not None and config.predicted_normal_weight > 0,
        camera_light=training.camera_light,
    )
    if spread and "base_color" in weights:
        terms["spread"] = spread_loss(weights["base_color"], source.seen.index_select(0, active))
    if shading is not None and config.normal_prior_weight > 0:
        seen = training.frozen.visible_ids[index]  # the normals this view's photo loss reaches
        terms["normal_prior"] = normal_prior(shading_normals[seen], normals[seen])
    if config.metallic_prior_weight > 0 and variant.dielectric_prior:
        terms["metallic_prior"] = merged[:, METALLIC_INDEX].mean()
    return terms, total_loss(terms, config)


def starting_camera_light(config: RefineConfig, inputs: RefineInputs, device) -> tuple[CameraLight | None, list[bool]]:
    """The flash refinement estimates beside the environment, starting at the environment's starting radiance, and the
    training views it lit, read once from the photos' EXIF (`config.camera_light`); None when it lit none."""
    lit = lit_views(config.camera_light, [v.path for v in inputs.views])
    if not any(lit):
        return None, lit
    distance = reference_distance([v.camera for v in inputs.views], inputs.bounds)
    return CameraLight.initial(config.envmap_init, distance, config.camera_light, device), lit


def starting_light(config: RefineConfig, light: Light | None, device) -> Light:
    """The light refinement starts from: a constant one of `config.light_model` to learn, or the known `light`, never
    optimised."""
    if light is None:
        return light_model(config.light_model).initial(config.envmap_init, config.envmap_height, device=device)
    return light.fixed().to(device)


def warm_up_or_reuse(training, materials, normals, envmap, config, generator, progress, warmed_lights) -> None:
    """The light's warm-up (`warm_up_light`), or its outcome (light and random state) found in `warmed_lights` for
    the same starting materials and settings; a warm-up run here is kept there for the next variant."""
    key = warm_up_key(materials, config)
    lights = [*envmap.parameters(), *(training.camera_light.parameters() if training.camera_light else ())]
    if warmed_lights is not None and key in warmed_lights:
        parameters, state = warmed_lights[key]
        with torch.no_grad():
            for parameter, value in zip(lights, parameters, strict=True):
                parameter.copy_(value)
        generator.set_state(state)
        return
    warm_up_light(training, materials, normals, envmap, config, generator, progress)
    if warmed_lights is not None:
        warmed_lights[key] = ([p.detach().clone() for p in lights], generator.get_state())


def with_fitted_metallic(
    materials: Tensor,  # [N, 5]
    normals: Tensor,  # [N, 3]
    envmap: Light | None,
    training: TrainingViews,
    targets: list[Tensor],  # V 2D maps [H, W, 5]
    config: RefineConfig,
) -> Tensor:  # [N, 5]
    """`materials` with the metallic fitted through refinement's frozen views to the 2D maps and, with a light, the
    photos; the rest of the materials, the normals and the light stay as refined."""
    light = None if envmap is None else envmap.fixed()
    flash = None if training.camera_light is None else training.camera_light.fixed()
    others = materials[:, :METALLIC_INDEX]  # the metallic is the last channel

    def photo(index: int, metallic: Tensor) -> Tensor:
        candidate = torch.cat([others, metallic[:, None].to(others)], dim=1)
        return view_losses(training, index, candidate, normals, light, config, False, False, flash)["photo"]

    fitted = fit_metallic(
        materials[:, METALLIC_INDEX].float(),
        training.frozen.render,
        [target[..., METALLIC_INDEX] for target in targets],
        [training.constants(index).surface for index in range(len(training))],
        config.metallic_fit,
        photo if light is not None else None,
    )
    materials = materials.clone()
    materials[:, METALLIC_INDEX] = fitted.to(materials)
    return materials
