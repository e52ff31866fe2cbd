"""The split-sum BRDF integration table (Karis 2013), computed in code.

For the specular lobe of `brdf.cook_torrance` with F0 factored out of Schlick's Fresnel,

    integral  f_spec(wi, wo) (n.wi)+ dwi  =  F0 * A(n.wo, r)  +  B(n.wo, r)

since F = F0 (1 - Fc) + Fc with Fc = (1 - wo.h)^5:  A = integral (1 - Fc) D V (n.wi)+ dwi  and
B = integral Fc D V (n.wi)+ dwi, V being the height-correlated Smith visibility. A and B depend only
on n.wo and the roughness, so they are tabulated once on a size x size grid (texel centres at
(i + 0.5) / size on both axes) and looked up bilinearly.

The integrals are estimated by importance sampling the GGX distribution of visible normals (Heitz
2018) on a deterministic Hammersley point set. Each sample then weighs G2(wi, wo) / G1(wo) <= 1, so
the estimate converges far faster than sampling D(h) (n.h), above all at grazing views: with 512
samples every entry is within 3e-3 of a 65k-sample reference (benchmarks/shading.py).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.render.shade.brdf import roughness_to_alpha, smith_g1, smith_visibility

DEFAULT_SIZE = 32
DEFAULT_SAMPLES = 512

_TABLES: dict[tuple, Tensor] = {}  # (size, samples, device, dtype) -> [size, size, 2]


def hammersley(count: int, dtype=torch.float64, device="cpu") -> Tensor:  # -> [count, 2] in [0, 1)
    """The 2D Hammersley point set: ((i + 0.5) / count, radical inverse of i in base 2)."""
    i = torch.arange(count, dtype=torch.int64, device=device)
    bits = torch.zeros(count, dtype=torch.int64, device=device)
    for k in range(32):  # reverse the low 32 bits of i
        bits |= ((i >> k) & 1) << (31 - k)
    return torch.stack([(i.to(dtype) + 0.5) / count, bits.to(dtype) / 2.0**32], dim=-1)


def sample_visible_normals(u: Tensor, n_dot_v: Tensor, alpha: Tensor) -> Tensor:  # [S, 2], [...], [...] -> [..., S, 3]
    """Half vectors h with density G1(wo) (wo.h)+ D(h) / (n.wo), in the frame n = +z, wo = (sin, 0, n.wo)."""
    nv, a = n_dot_v[..., None], alpha[..., None]  # [..., 1]
    # the view in the stretched (alpha = 1) configuration, where visible normals are a projected disk
    vx, vz = a * torch.sqrt((1.0 - nv * nv).clamp_min(0.0)), nv
    length = torch.sqrt(vx * vx + vz * vz)
    vx, vz = vx / length, vz / length
    radius, phi = torch.sqrt(u[:, 0]), 2.0 * math.pi * u[:, 1]  # [S]
    t1, t2 = radius * torch.cos(phi), radius * torch.sin(phi)
    s = 0.5 * (1.0 + vz)
    t2 = (1.0 - s) * torch.sqrt(1.0 - t1 * t1) + s * t2  # [..., S]
    tz = torch.sqrt((1.0 - t1 * t1 - t2 * t2).clamp_min(0.0))
    # tangent frame of the stretched view: T1 = (0, 1, 0), T2 = (-vz, 0, vx), view = (vx, 0, vz)
    hx, hy, hz = -t2 * vz + tz * vx, t1.expand_as(t2), t2 * vx + tz * vz
    h = torch.stack([a * hx, a * hy, hz.clamp_min(0.0)], dim=-1)  # unstretch
    return h / h.norm(dim=-1, keepdim=True)


def integrate_split_sum(n_dot_v: Tensor, roughness: Tensor, samples: int = DEFAULT_SAMPLES) -> Tensor:
    """A and B [..., 2] for n.wo [...] and perceptual roughness [...].

    With pdf(wi) = G1(wo) D(h) / (4 n.wo), a sample contributes D V (n.wi) / pdf = 4 V (n.wi) (n.wo) / G1(wo)
    (= G2 / G1), times (1 - Fc) to A and Fc to B.
    """
    n_dot_v, roughness = torch.broadcast_tensors(n_dot_v, roughness)
    alpha = roughness_to_alpha(roughness)
    nv = n_dot_v.clamp(1e-4, 1.0)
    h = sample_visible_normals(hammersley(samples, nv.dtype, nv.device), nv, alpha)  # [..., S, 3]
    sin_v = torch.sqrt(1.0 - nv * nv)[..., None]
    v_dot_h = sin_v * h[..., 0] + nv[..., None] * h[..., 2]  # [..., S]
    n_dot_l = 2.0 * v_dot_h * h[..., 2] - nv[..., None]  # z of wi = 2 (wo.h) h - wo
    nv_, alpha_ = nv[..., None], alpha[..., None]
    weight = 4.0 * smith_visibility(n_dot_l, nv_, alpha_) * n_dot_l * nv_ / smith_g1(nv_, alpha_)
    weight = torch.where(n_dot_l > 0, weight, torch.zeros_like(weight))
    fc = (1.0 - v_dot_h.clamp(0.0, 1.0)) ** 5
    return torch.stack([(weight * (1.0 - fc)).mean(-1), (weight * fc).mean(-1)], dim=-1)


def brdf_lut(size: int = DEFAULT_SIZE, samples: int = DEFAULT_SAMPLES, device=None, dtype=torch.float32) -> Tensor:
    """The table [size (n.wo), size (roughness), 2 (A, B)], computed once per (size, samples, device, dtype)."""
    device = torch.device(device) if device is not None else torch.device("cpu")
    key = (size, samples, str(device), dtype)
    if key not in _TABLES:
        base_key = (size, samples, "cpu", torch.float64)
        if base_key not in _TABLES:
            centres = (
                torch.arange(size, dtype=torch.float64, device="cpu") + 0.5
            ) / size  # integrated once, on the CPU
            nv, r = torch.meshgrid(centres, centres, indexing="ij")
            _TABLES[base_key] = integrate_split_sum(nv, r, samples)
        _TABLES[key] = _TABLES[base_key].to(device=device, dtype=dtype)
    return _TABLES[key]


def _lut_image(size: int, device, dtype) -> Tensor:  # -> [1, 2, size (n.v) = rows, size (r) = columns]
    key = ("image", size, str(device), dtype)
    if key not in _TABLES:
        _TABLES[key] = brdf_lut(size, device=device, dtype=dtype).permute(2, 0, 1)[None].contiguous()
    return _TABLES[key]


def brdf_scale_bias(n_dot_v: Tensor, roughness: Tensor, size: int = DEFAULT_SIZE) -> tuple[Tensor, Tensor]:
    """`lookup_brdf_lut` as the two tables' values (A, B), [...] each, n.wo and roughness [...] of one shape."""
    image = _lut_image(size, n_dot_v.device, n_dot_v.dtype)
    # grid_sample: x indexes columns (roughness), y rows (n.v); align_corners=False puts texel centres at
    # (i + 0.5) / size
    grid = (torch.stack([roughness, n_dot_v], dim=-1) * 2.0 - 1.0).view(1, 1, -1, 2)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)  # [1, 2, 1, P]
    return out.view(2, *n_dot_v.shape).unbind(0)


def lookup_brdf_lut(n_dot_v: Tensor, roughness: Tensor, size: int = DEFAULT_SIZE) -> Tensor:  # [...], [...] -> [..., 2]
    """Bilinear lookup of (A, B), clamped to the outermost texel centres; differentiable in both inputs."""
    return torch.stack(brdf_scale_bias(*torch.broadcast_tensors(n_dot_v, roughness), size), dim=-1)
