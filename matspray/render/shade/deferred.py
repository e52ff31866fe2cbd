"""Deferred PBR shading: image-based lighting of a G-buffer by the split-sum approximation.

    rgb = E(n) * base_color (1 - metallic) / pi  +  L_spec(d, r) * (F0 A(n.wo, r) + B(n.wo, r))

E is the environment's irradiance (cosine convolution), L_spec its GGX-prefiltered radiance and (A, B)
the BRDF integration table; together they approximate the integral of L(wi) f_r(wi, wo) (n.wi)+ over
the hemisphere with `brdf.cook_torrance` as f_r (diffuse not scaled by 1 - F, as there).

d is the specular lobe's dominant direction: the mirror direction reflect(-wo, n) pulled towards the
normal as roughness grows (Lagarde & de Rousiers 2014, "Moving Frostbite to PBR", with alpha = r^2),
because a rough lobe seen off-normal leans towards n. Against the numerically integrated reference
(`shade_by_quadrature`, benchmarks/shading.py) it brings rough metals (r = 0.9) from up to 18 % error
down to 3 %, and r = 0.5 from 11 % to 4 %, except for a normal near horizontal under a bright sky,
where it raises the r = 0.5 error from 5 % to 13 %.

Normals need not be unit length (rasterized normals are blends); they are normalised here. Gaussian
normals carry no reliable sign, so a normal facing away from the viewer (n.wo < 0) is flipped to face
it; the table lookup holds n.wo at its first texel centre (1 / 64) from below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.data.camera import Camera
from matspray.material import N_CHANNELS, stack, unstack
from matspray.render.shade.brdf import DIELECTRIC_F0, MIN_ROUGHNESS, cook_torrance, dot, reflect, roughness_to_alpha
from matspray.render.shade.brdf_lut import brdf_scale_bias
from matspray.render.shade.envmap import sample_latlong
from matspray.render.shade.latlong import pixel_directions, pixel_solid_angles
from matspray.render.shade.light import Light, PrefilteredLight


@dataclass
class GBuffer:
    """Material and normal maps rasterized for one camera (values not premultiplied by alpha)."""

    base_color: Tensor  # [H, W, 3] linear
    roughness: Tensor  # [H, W] perceptual
    metallic: Tensor  # [H, W]
    normals: Tensor  # [H, W, 3] world space, any length
    alpha: Tensor  # [H, W] coverage in [0, 1]
    # [H, W, 6] diffuse and specular RGB light scales (`render.visibility`); None = unshadowed
    shadow: Tensor | None = None

    @classmethod
    def from_accumulated(
        cls,
        base_color: Tensor,
        roughness: Tensor,
        metallic: Tensor,
        normals: Tensor,
        alpha: Tensor,
        shadow: Tensor | None = None,
    ):
        """From alpha-blended sums over a black background (sum_i w_i value_i, with sum_i w_i = alpha):
        divides the materials (and shadow factors) by alpha. Normals keep their blend; shading normalises them."""
        cover = alpha.clamp_min(1e-6)
        shadow = None if shadow is None else shadow / cover[..., None]
        return cls(base_color / cover[..., None], roughness / cover, metallic / cover, normals, alpha, shadow)

    @classmethod
    def from_blended(cls, blended: Tensor, alpha: Tensor):
        """`from_accumulated` of blended per-Gaussian features [H, W, 8 | 14] laid out as the 5 material
        channels (`matspray.material`), normal 3 and optionally the 6 shadow factors (`render.visibility`)."""
        base_color, roughness, metallic = unstack(blended[..., :N_CHANNELS])
        normals = blended[..., N_CHANNELS : N_CHANNELS + 3]
        shadow = blended[..., N_CHANNELS + 3 : N_CHANNELS + 9] if blended.shape[-1] > N_CHANNELS + 3 else None
        return cls.from_accumulated(base_color, roughness, metallic, normals, alpha, shadow)

    @property
    def materials(self) -> Tensor:  # [H, W, 5]
        return stack(self.base_color, self.roughness, self.metallic)


def specular_direction(n: Tensor, wo: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [..., 3], [...] -> [..., 3]
    """Dominant direction of the specular lobe: lerp(n, reflect(-wo, n), s (sqrt(s) + alpha)), s = 1 - alpha; not of
    unit length (lookups read only the direction: normalise it for anything else)."""
    alpha = roughness_to_alpha(roughness)[..., None]
    smooth = 1.0 - alpha
    mirror = reflect(-wo, n)
    # s^1.5 + s alpha rather than s (sqrt(s) + alpha): the same value, but a finite gradient at s = 0 (roughness 1)
    return torch.lerp(n, mirror, smooth.pow(1.5) + smooth * alpha)


def shade(
    base_color: Tensor,  # [..., 3] linear
    roughness: Tensor,  # [...] perceptual
    metallic: Tensor,  # [...]
    normals: Tensor,  # [..., 3] world space, any length
    view_dirs: Tensor,  # [..., 3] from the surface towards the camera (wo), any length
    light: Light | PrefilteredLight,
    shadow: Tensor | None = None,  # [..., 6] diffuse and specular RGB light scales; None = unshadowed
) -> Tensor:  # [..., 3] outgoing linear radiance
    """Split-sum image-based lighting. Pass a prefiltered light (`Light.prefilter`) to reuse one prefiltering."""
    wo = F.normalize(view_dirs, dim=-1, eps=1e-12)
    return shade_unit(base_color, roughness, metallic, normals, wo, light, shadow)


def shade_unit(
    base_color: Tensor,  # [..., 3] linear
    roughness: Tensor,  # [...] perceptual
    metallic: Tensor,  # [...]
    normals: Tensor,  # [..., 3] world space, any length
    wo: Tensor,  # [..., 3] unit, from the surface towards the camera
    light: Light | PrefilteredLight,
    shadow: Tensor | None = None,  # [..., 6] diffuse and specular RGB light scales; None = unshadowed
) -> Tensor:  # [..., 3] outgoing linear radiance
    """`shade` with unit view directions, e.g. a camera's, normalised once (`view_directions`)."""
    light = light.prefilter()  # a prefiltered light returns itself
    n = F.normalize(normals, dim=-1, eps=1e-12)
    n_dot_v = dot(n, wo)
    facing = torch.where(n_dot_v < 0, -1.0, 1.0)  # [...] turns a normal facing away towards the viewer
    n = n * facing[..., None]
    cos = n_dot_v * facing  # n.wo of the turned normal
    r = roughness.clamp(MIN_ROUGHNESS, 1.0)
    scale, bias = brdf_scale_bias(cos, r)  # [...] each (n.wo below the table's first texel reads that texel)
    dielectric = 1.0 - metallic[..., None]
    specular_weight = (DIELECTRIC_F0 * dielectric + base_color * metallic[..., None]) * scale[..., None]  # F0 A
    lobe = specular_direction(n, wo, r)
    specular_light, irradiance = light.lookup(lobe, r, n)
    specular = specular_light * (specular_weight + bias[..., None])
    diffuse = irradiance * (base_color * dielectric) / math.pi
    if shadow is not None:
        diffuse, specular = diffuse * shadow[..., :3], specular * shadow[..., 3:]
    return diffuse + specular


def view_directions(camera: Camera, device=None, dtype=torch.float32) -> Tensor:  # -> [H, W, 3] unit
    """wo of every pixel: the reverse of the camera ray through its centre, normalised."""
    _, ray_dirs = camera.to(device).rays()  # [H * W, 3], row-major
    return F.normalize(-ray_dirs.reshape(camera.height, camera.width, 3).to(dtype), dim=-1, eps=1e-12)


def shade_gbuffer(
    gbuffer: GBuffer,
    camera: Camera,
    light: Light | PrefilteredLight,
    background: Tensor | None = None,  # [3] or [H, W, 3] linear; None = black
    view_dirs: Tensor | None = None,  # [H, W, 3] `view_directions(camera)` when the caller keeps them
) -> Tensor:  # [H, W, 3]
    """Shade every pixel and composite over the background with the G-buffer's alpha.

    With only a G-buffer (no surface positions) the view direction of a pixel is the reverse of the
    camera ray through its centre, wo = -ray_dir: exact for a pinhole camera up to the ray's offset
    from the pixel centre, and independent of the depth.
    """
    height, width = camera.height, camera.width
    if tuple(gbuffer.alpha.shape) != (height, width):
        raise ValueError(f"G-buffer is {tuple(gbuffer.alpha.shape)} but the camera is {height} x {width}")
    if view_dirs is None:
        view_dirs = view_directions(camera, gbuffer.normals.device, gbuffer.normals.dtype)
    rgb = shade_unit(
        gbuffer.base_color, gbuffer.roughness, gbuffer.metallic, gbuffer.normals, view_dirs, light, gbuffer.shadow
    )
    alpha = gbuffer.alpha[..., None]
    if background is None:
        return rgb * alpha
    return rgb * alpha + background.to(rgb) * (1.0 - alpha)


def shade_by_quadrature(
    base_color: Tensor,  # [..., 3]
    roughness: Tensor,  # [...]
    metallic: Tensor,  # [...]
    normals: Tensor,  # [..., 3] unit
    view_dirs: Tensor,  # [..., 3] unit
    light_map: Tensor,  # [H, 2H, 3] linear radiance
    rows: int = 256,
) -> Tensor:  # [..., 3]
    """The reference that `shade` approximates: integral L(wi) f_r(wi, wo) (n.wi)+ dwi, summed over the
    pixel centres of a rows x 2 rows lat-long grid of directions with their solid angles, L being the
    map's bilinear radiance and f_r `brdf.cook_torrance`. O(points x rows^2): for tests and benchmarks."""
    base_color, normals, view_dirs = (x[..., None, :] for x in (base_color, normals, view_dirs))
    roughness, metallic = roughness[..., None], metallic[..., None]
    directions = pixel_directions(rows, 2 * rows, device=light_map.device, dtype=light_map.dtype).reshape(-1, 3)
    solid_angles = pixel_solid_angles(rows, 2 * rows, device=light_map.device, dtype=light_map.dtype).reshape(-1)
    total = 0.0
    for wi, dw in zip(directions.split(1 << 15), solid_angles.split(1 << 15)):  # bounds the memory
        radiance = sample_latlong(light_map, wi) * dw[:, None]  # [P, 3]
        f = cook_torrance(base_color, roughness, metallic, normals, view_dirs, wi)  # [..., P, 3]
        total = total + (f * radiance * dot(normals, wi).clamp_min(0.0)[..., None]).sum(-2)
    return total
