"""The image-sized part of a refinement step as pure functions of tensors, which `matspray.device.Graphed` runs as
CUDA graphs on a CUDA device (the deferred shading and every loss of a view in one launch each way; the
environment map's prefiltering and its prior in another), the material losses they use, and `view_losses`, which
gathers a training view's inputs for them, with `total_loss`, their weighted sum.

A step on a GPU is otherwise a few hundred small kernels, each waiting on Python to launch it: the G-buffer's
division by the coverage, the split-sum shading's lookups, the sRGB curve, SSIM and the L1 terms. The functions here
compute exactly what `view_losses` computed op by op before (tests/test_refine_terms.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.geometry.losses import normal_map_loss, photometric_loss
from matspray.material import BASE_COLOR, METALLIC_INDEX, N_CHANNELS, unstack
from matspray.render.shade.brdf import camera_light_radiance
from matspray.render.shade.deferred import shade_unit
from matspray.render.shade.envmap import PrefilteredEnvironment, prefilter_log_map
from matspray.render.shade.light import Light, PrefilteredLight
from matspray.render.shade.visibility import gaussian_shadows

DEFAULT_HUBER_DELTA = 0.05  # linear base colour; the residual where "huber" turns from quadratic to linear


# ------------------------------------------------------------------------------------------ material losses
def masked_l1(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:  # [H, W, C], [H, W, C], [H, W] -> []
    weight = mask[..., None].expand_as(pred)
    return weighted_l1(pred, target, weight, weight.sum().clamp_min(1.0))


def weighted_l1(pred: Tensor, target: Tensor, weight: Tensor, total: Tensor) -> Tensor:  # [H, W, C] x3, [] -> []
    """Sum of the weighted absolute errors over `total` (the weights' sum, at least 1: `masked_l1`)."""
    return ((pred - target).abs() * weight).sum() / total


def scale_invariant_l1(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:  # [H, W, C], [H, W, C], [H, W] -> []
    """masked L1 of s * pred against target, s the least-squares scale of pred onto target over the mask
    (clamped to [0.1, 10]): blind to a global brightness error of either side."""
    weight = mask[..., None].expand_as(pred)
    scale = (pred * target * weight).sum() / (pred * pred * weight).sum().clamp_min(1e-8)
    return masked_l1(scale.clamp(0.1, 10.0) * pred, target, mask)


def masked_huber(
    pred: Tensor, target: Tensor, mask: Tensor, delta: float
) -> Tensor:  # [H, W, C], [H, W, C], [H, W] -> []
    """Masked Huber loss: r^2 / (2 delta) for a residual |r| < delta, |r| - delta / 2 above (L1's slope, 1)."""
    weight = mask[..., None].expand_as(pred)
    return (
        torch.nn.functional.smooth_l1_loss(pred, target, reduction="none", beta=delta) * weight
    ).sum() / weight.sum().clamp_min(1.0)


def metallic_tilt(
    maps: Tensor, target: Tensor, weight: Tensor, total: Tensor, quantile: float
) -> Tensor:  # [H, W, 5] x2, [H, W], [] -> []
    """What turns weighted L1 into the pinball loss of `quantile` on the metallic channel: 2 rho_q(e) =
    |e| + (1 - 2 q) e for the error e = map - target, so that over the views the loss is smallest at their
    q-quantile instead of their median. `weight` is the metallic channel's and `total` the L1's divisor; q = 0.5
    (L1) needs no term."""
    error = maps[..., METALLIC_INDEX] - target[..., METALLIC_INDEX]
    return (1.0 - 2.0 * quantile) * (error * weight).sum() / total


def material_loss(
    maps: Tensor,
    target: Tensor,
    mask: Tensor,
    basecolor_loss: str,
    huber_delta: float = DEFAULT_HUBER_DELTA,
    metallic_quantile: float = 0.5,
) -> Tensor:
    """L1 of rendered material maps [H, W, 5] against the 2D maps [H, W, 5] over the mask [H, W], averaged over the 5
    channels; the base color channels scale-invariant or Huber (`huber_delta`) when `basecolor_loss` says so, the
    metallic the pinball loss of `metallic_quantile` (`metallic_tilt`)."""

    def with_tilt(l1: Tensor, channels: int) -> Tensor:  # `l1` averaged over `channels` channels of the mask
        if metallic_quantile == 0.5:
            return l1
        total = (channels * mask.sum()).clamp_min(1.0)  # masked_l1's divisor
        return l1 + metallic_tilt(maps, target, mask, total, metallic_quantile)

    if basecolor_loss == "l1":
        return with_tilt(masked_l1(maps, target, mask), N_CHANNELS)
    if basecolor_loss == "huber":
        base = masked_huber(maps[..., BASE_COLOR], target[..., BASE_COLOR], mask, huber_delta)
    else:
        base = scale_invariant_l1(maps[..., BASE_COLOR], target[..., BASE_COLOR], mask)
    rest = slice(BASE_COLOR.stop, N_CHANNELS)
    rest_l1 = with_tilt(masked_l1(maps[..., rest], target[..., rest], mask), N_CHANNELS - BASE_COLOR.stop)
    return (3.0 * base + 2.0 * rest_l1) / N_CHANNELS


# ------------------------------------------------------------------------------------------ a view's terms
@dataclass(frozen=True)
class TermOptions:
    """What a view's terms are made of besides tensors (the key of its captured graph)."""

    material: str | None  # the material loss ("l1", "huber", "scale-invariant"), None: no material term
    huber_delta: float
    predicted_normals: bool  # the angle to the view's predicted normal map
    photo: bool  # the PBR render against the photo (with an environment)
    ssim_weight: float  # 1 - photo_l1_weight
    shadowed: bool  # the blended features end with the 6 shadow factors
    levels: tuple = ()  # the prefiltered light's layout (`PrefilteredLight.layout`, with `photo`): a lat-long
    # environment's roughness levels
    metallic_quantile: float = 0.5  # the material term's quantile of the views' metallic (`metallic_tilt`)
    light_type: type = PrefilteredEnvironment  # the prefiltered light's type (`Light.prefiltered_type`)
    camera_light: bool = False  # with `photo`: a flash at the camera adds its light (`refine.camera_light`)

    @property
    def names(self) -> tuple[str, ...]:
        """The terms `view_terms` returns, in order."""
        chosen = (self.material is not None, self.predicted_normals, self.photo)
        return tuple(name for name, on in zip(("material", "predicted_normals", "photo"), chosen) if on)


def view_terms(
    options: TermOptions,
    blended: Tensor,  # [H, W, 8 | 14] the Gaussians' materials (5), oriented normals (3) (and shadow factors (6))
    # blended over black
    alpha: Tensor,  # [H, W] the frozen coverage
    cover: Tensor,  # [H, W, 1] the coverage, clamped (`refine.ViewConstants`)
    view_dirs: Tensor,  # [H, W, 3] unit, towards the camera
    photo: Tensor,  # [H, W, 3] sRGB over black
    target: Tensor,  # [H, W, 5] the view's 2D material maps
    surface: Tensor,  # [H, W] where the 2D maps count
    surface_weight: Tensor,  # [H, W, 5] `surface` per channel
    surface_count: Tensor,  # [] its sum, at least 1
    normal_map: Tensor,  # [H, W, 3] the predicted normals (read with `predicted_normals`)
    flash: Tensor,  # [H, W, 3] the camera light's irradiance I (d0 / d)^2 (read with `camera_light`)
    *light: Tensor,  # with `photo`: the prefiltered environment's images (`light_images`), specular runs then
    # irradiance
) -> Tensor:  # [T] the terms of `options.names`
    """The loss terms of one view from its blended features: the G-buffer (coverage divided out once), L1 of its
    material maps against the 2D maps, the angle of its normals to the predicted ones, and 0.8 L1 + 0.2 D-SSIM of its
    split-sum shading (in sRGB; with a camera light, plus its flash: `brdf.camera_light_radiance`) against the photo.
    No host reads: what a CUDA graph can capture."""
    maps = blended[..., :N_CHANNELS] / cover  # [H, W, 5]
    normals = blended[..., N_CHANNELS : N_CHANNELS + 3]
    terms = []
    if options.material == "l1":
        term = weighted_l1(maps, target, surface_weight, surface_count)
        if options.metallic_quantile != 0.5:
            metal = surface_weight[..., METALLIC_INDEX]
            term = term + metallic_tilt(maps, target, metal, surface_count, options.metallic_quantile)
        terms.append(term)
    elif options.material is not None:
        quantile = options.metallic_quantile
        terms.append(material_loss(maps, target, surface, options.material, options.huber_delta, quantile))
    if options.predicted_normals:
        terms.append(normal_map_loss(normals, normal_map, surface))
    if options.photo:
        shadow = blended[..., N_CHANNELS + 3 :] / cover if options.shadowed else None
        environment = options.light_type.from_tensors(options.levels, light)
        base_color, roughness, metallic = unstack(maps)
        # `deferred.shade_gbuffer` over black: the shaded G-buffer times its coverage
        shaded = shade_unit(base_color, roughness, metallic, normals, view_dirs, environment, shadow)  # [H, W, 3]
        if options.camera_light:
            shaded = shaded + camera_light_radiance(base_color, roughness, metallic, normals, view_dirs, flash)
        rendered = shaded * alpha[..., None]
        terms.append(photometric_loss(linear_to_srgb(rendered), photo, options.ssim_weight))
    return torch.stack(terms)


def light_images(environment: PrefilteredLight) -> tuple[Tensor, ...]:
    """The prefiltered light as `view_terms` takes it (`PrefilteredLight.tensors`)."""
    return environment.tensors()


prefiltered_light = prefilter_log_map  # a learnable lat-long map's prefiltering step (`Light.step_function`)


# ------------------------------------------------------------------------------------------ a view's losses
def view_losses(
    training,  # refine.loop.TrainingViews
    index: int,
    materials: Tensor,
    normals: Tensor,
    envmap: Light | None,
    config,  # refine.loop.RefineConfig
    with_material: bool = True,
    with_normals: bool = False,
    camera_light=None,  # refine.camera_light.CameraLight: a flash on the views that had one
) -> dict[str, Tensor]:
    """The losses of training view `index`: L1 of the rasterized material maps against the view's 2D maps
    ("material", when `with_material`), and 0.8 L1 + 0.2 D-SSIM of the PBR render against the photo
    ("photo", only with an environment map), and with `with_normals` the angle of the rendered normals to the view's
    predicted normal map ("predicted_normals", when there is one); with a `camera_light`, a view whose photo had a
    flash is shaded with it too. materials [N, 5], normals [N, 3] any
    orientation. Past the render, the terms are one function of tensors (`view_terms`), and so is the
    learnable light's prefiltering: CUDA graphs on a CUDA device (`TrainingViews`)."""
    frozen, view, constants = training.frozen, training.views[index], training.constants(index)
    oriented = frozen.orient_normals(index, normals)
    features = [materials, oriented]
    light, light_tv = training.environment(envmap, config.light_tv_weight > 0)
    if (
        light is not None and training.visibility is not None
    ):  # only for the Gaussians this view sees: the rest blend with weight 0
        seen = frozen.visible_ids[index]
        # index_select: the same rows as indexing by `seen`, several times faster on the CPU for [N, D] visibility
        picked = (x.index_select(0, seen) for x in (training.visibility, oriented, frozen.means, materials))
        shadows = gaussian_shadows(*picked, view.camera, light)
        features.append(materials.new_zeros(len(materials), 6).index_copy(0, seen, shadows))
    blended, alpha = frozen.render(index, torch.cat(features, dim=-1))  # [H, W, 8 or 14], [H, W]
    flashed = light is not None and camera_light is not None and constants.falloff is not None
    material = None
    if with_material:  # without the PBR loss nothing sets the scale
        scale_free = config.basecolor_loss == "scale-invariant"
        material = "l1" if scale_free and light is None else config.basecolor_loss
    options = TermOptions(
        material,
        config.basecolor_huber_delta,
        with_normals and training.normal_maps is not None,
        light is not None,
        1.0 - config.photo_l1_weight,
        blended.shape[-1] > N_CHANNELS + 3,
        light.layout if light is not None else (),
        config.metallic_quantile,
        type(light) if light is not None else PrefilteredEnvironment,
        flashed,
    )
    tensors = (
        blended,
        alpha,
        constants.cover,
        constants.view_dirs,
        constants.photo,
        training.targets[index] if material is not None else constants.photo,  # read only with the material term
        constants.surface,
        constants.surface_weight,
        constants.surface_count,
        training.normal_maps[index] if options.predicted_normals else constants.view_dirs,  # read only if predicted
        constants.falloff * camera_light.intensity if flashed else constants.view_dirs,  # read only if flashed
        *(light_images(light) if light is not None else ()),
    )
    stacked = training.terms(options, *tensors)  # [T]
    terms = dict(zip(options.names, stacked.unbind(0)))
    if light_tv is not None:
        terms["light_tv"] = light_tv
    return terms


def total_loss(terms: dict[str, Tensor], config) -> Tensor:  # config: refine.loop.RefineConfig
    """The weighted sum of the loss terms (a weight of 1 multiplies nothing)."""
    weights = {
        "material": config.material_weight,
        "photo": config.photo_weight,
        "light_tv": config.light_tv_weight,
        "spread": config.basecolor_spread_weight,
        "normal_prior": config.normal_prior_weight,
        "predicted_normals": config.predicted_normal_weight,
        "metallic_prior": config.metallic_prior_weight,
    }
    weighted = [value if weights[name] == 1.0 else weights[name] * value for name, value in terms.items()]
    total = weighted[0]
    for value in weighted[1:]:
        total = total + value
    return total
