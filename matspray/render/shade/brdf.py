"""Cook-Torrance GGX microfacet BRDF with a Lambert diffuse lobe (the metallic-roughness model).

    f_r(wi, wo) = base_color * (1 - metallic) / pi  +  F(wo.h) D(n.h) V(n.wi, n.wo)

- D: GGX / Trowbridge-Reitz normal distribution with alpha = roughness^2 (perceptual roughness, as
  UE4, nvdiffrec and Mitsuba's principled BSDF); roughness is clamped to MIN_ROUGHNESS.
- V = G / (4 n.wi n.wo): Smith masking-shadowing, height-correlated form.
- F: Schlick's approximation with F0 = lerp(0.04, base_color, metallic).

The diffuse lobe is NOT scaled by (1 - F): like nvdiffrec and R3DGS, diffuse and specular are added.
The split-sum shading in `deferred.py` uses the same convention, so the two agree; the price is that
a white dielectric reflects slightly more than it receives: 1 + its specular albedo, which is about
0.04 at normal incidence and grows towards grazing angles.

All directions are world-space unit vectors; wo points from the surface towards the viewer, wi
towards the light. Everything is linear RGB.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

MIN_ROUGHNESS = 0.04  # perceptual; alpha = 0.0016. Keeps D finite and gradients tame.
DIELECTRIC_F0 = 0.04  # reflectance at normal incidence of a dielectric with IOR ~1.5


def dot(a: Tensor, b: Tensor) -> Tensor:  # [..., 3], [..., 3] -> [...]
    return (a * b).sum(-1)


def reflect(d: Tensor, n: Tensor) -> Tensor:  # [..., 3] incident (towards the surface), [..., 3] unit -> [..., 3]
    """Mirror direction of `d` about the plane with normal `n`: d - 2 (d.n) n."""
    return d - 2.0 * dot(d, n)[..., None] * n


def roughness_to_alpha(roughness: Tensor) -> Tensor:  # [...] perceptual -> [...] GGX alpha
    return roughness.clamp(MIN_ROUGHNESS, 1.0) ** 2


def ggx_ndf(n_dot_h: Tensor, alpha: Tensor) -> Tensor:  # [...], [...] -> [...]
    """GGX normal distribution D(h); integrates to 1 against (n.h) over the hemisphere of h."""
    a2 = alpha * alpha
    c2 = n_dot_h.clamp(0.0, 1.0) ** 2
    denom = c2 * (a2 - 1.0) + 1.0
    return a2 / (math.pi * denom * denom)


def smith_visibility(n_dot_l: Tensor, n_dot_v: Tensor, alpha: Tensor) -> Tensor:  # [...] x3 -> [...]
    """Height-correlated Smith visibility V = G2(l, v) / (4 n.l n.v) for GGX (Heitz 2014)."""
    a2 = alpha * alpha
    nl, nv = n_dot_l.clamp_min(0.0), n_dot_v.clamp_min(0.0)
    lambda_v = nl * torch.sqrt(nv * nv * (1.0 - a2) + a2)
    lambda_l = nv * torch.sqrt(nl * nl * (1.0 - a2) + a2)
    return 0.5 / (lambda_v + lambda_l).clamp_min(1e-12)


def smith_g1(n_dot_v: Tensor, alpha: Tensor) -> Tensor:  # [...], [...] -> [...]
    """Smith masking of one direction for GGX: 1 / (1 + Lambda), Lambda = (sqrt(1 + a^2 tan^2) - 1) / 2."""
    nv = n_dot_v.clamp_min(1e-12)
    a2 = alpha * alpha
    return 2.0 * nv / (nv + torch.sqrt(nv * nv * (1.0 - a2) + a2))


def fresnel_schlick(f0: Tensor, v_dot_h: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
    weight = (1.0 - v_dot_h.clamp(0.0, 1.0)) ** 5
    return f0 + (1.0 - f0) * weight[..., None]


def specular_f0(base_color: Tensor, metallic: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
    """F0 = lerp(0.04, base_color, metallic)."""
    m = metallic[..., None]
    return DIELECTRIC_F0 * (1.0 - m) + base_color * m


def diffuse_albedo(base_color: Tensor, metallic: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
    """Lambert albedo base_color * (1 - metallic); the diffuse BRDF is this over pi."""
    return base_color * (1.0 - metallic[..., None])


def cook_torrance(
    base_color: Tensor,  # [..., 3] linear
    roughness: Tensor,  # [...] perceptual, in [0, 1]
    metallic: Tensor,  # [...] in [0, 1]
    n: Tensor,  # [..., 3] unit normal
    wo: Tensor,  # [..., 3] unit, towards the viewer
    wi: Tensor,  # [..., 3] unit, towards the light
) -> Tensor:  # [..., 3] f_r(wi, wo), zero where wi or wo is below the surface
    """The BRDF value f_r(wi, wo) (no cosine factor)."""
    alpha = roughness_to_alpha(roughness)
    n_dot_l, n_dot_v = dot(n, wi), dot(n, wo)
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    specular = fresnel_schlick(specular_f0(base_color, metallic), dot(wo, h))
    specular = specular * (ggx_ndf(dot(n, h), alpha) * smith_visibility(n_dot_l, n_dot_v, alpha))[..., None]
    f = diffuse_albedo(base_color, metallic) / math.pi + specular
    above = (n_dot_l > 0) & (n_dot_v > 0)
    return f * above[..., None].to(f.dtype)


def camera_light_radiance(
    base_color: Tensor,  # [..., 3] linear
    roughness: Tensor,  # [...] perceptual
    metallic: Tensor,  # [...]
    normals: Tensor,  # [..., 3] world space, any length and sign
    wo: Tensor,  # [..., 3] unit, towards the camera
    irradiance: Tensor,  # [..., 3] what a point light at the camera delivers there, facing it (I / d^2)
) -> Tensor:  # [..., 3] outgoing linear radiance towards the camera
    """A point light at the camera's centre (a flash), seen by that camera: E f_r(wo, wo) (n.wo), wi = wo. The normal
    is turned to face the viewer, as split-sum shading turns it (`deferred.shade_unit`); a flash casts no shadow that
    its camera sees."""
    n = torch.nn.functional.normalize(normals, dim=-1, eps=1e-12)
    n = n * torch.where(dot(n, wo) < 0, -1.0, 1.0)[..., None]
    f = cook_torrance(base_color, roughness, metallic, n, wo, wo)  # [..., 3]
    return f * (irradiance * dot(n, wo).clamp_min(0.0)[..., None])
