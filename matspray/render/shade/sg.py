"""A light made of spherical Gaussians (SG): L(v) = sum_k mu_k exp(lambda_k (v . xi_k - 1)), a second `light.Light`.

K lobes, each with a unit axis xi [3], a sharpness lambda > 0 and an RGB amplitude mu >= 0, all learnable (stored as
a free vector, log lambda and log mu). Split-sum shading reads it without a map:

- specular: the split-sum lobe of roughness r (the GGX lobe D V (r.l)+ under n = v = r, normalised, as
  `envmap.prefilter_latlong` convolves a map with) is replaced by a normalised SG around the lobe direction with the
  same mean cosine (`lobe_sharpness`, solved once per roughness level, interpolated in log between levels); the light
  against it is a sum of SG products, each in closed form: int exp(a . v) dv = 4 pi sinh|a| / |a|;
- diffuse: E(n) = sum_k mu_k int exp(lambda_k (v . xi_k - 1)) (n . v)+ dv, which depends only on lambda_k and
  n . xi_k. It reduces to one integral over the angle from the axis (the azimuth's part is closed-form), tabulated
  once on a (log lambda, n . xi) grid and read bilinearly (`cosine_table`);
- prior: the total variation of its log radiance drawn on a lat-long grid, the lat-long map's own prior;
- save: its lat-long drawing (`height` rows) where the lat-long map goes, which every reader of a light reads, and
  its lobes beside it (`.sg.json`), which `load` reads back.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matspray.data.images import write_image
from matspray.errors import file_error
from matspray.files import write_json
from matspray.render.shade.brdf import ggx_ndf, smith_visibility
from matspray.render.shade.envmap import DEFAULT_LEVELS, MIN_RADIANCE, _level_weights, level_alpha
from matspray.render.shade.latlong import pixel_directions, total_variation
from matspray.render.shade.light import Light, PrefilteredLight
from matspray.rundir import read_record

LOBES_PER_ROW = 2  # lobes per row of the light's lat-long drawing (`RefineConfig.envmap_height`)
TABLE_SHARPNESS = (0.05, 4000.0)  # the diffuse table's range of lambda (log-spaced); beyond it, its edge
TABLE_SIZE = (64, 129)  # (lambda, n . xi) samples of the diffuse table
_TABLES: dict[tuple, Tensor] = {}


# ------------------------------------------------------------------------------------------ closed forms
def sg_radiance(axes: Tensor, sharpness: Tensor, amplitudes: Tensor, directions: Tensor) -> Tensor:
    """[K, 3] unit, [K], [K, 3], [..., 3] unit -> [..., 3] the mixture's radiance along each direction."""
    lobes = torch.exp(sharpness * (directions @ axes.T - 1.0))  # [..., K]
    return lobes @ amplitudes


def sg_integral(sharpness: Tensor) -> Tensor:  # [...] -> [...] int exp(lambda (v . xi - 1)) dv = 2 pi (1 - e^-2l) / l
    return 2 * math.pi * -torch.expm1(-2 * sharpness) / sharpness


def sg_product_integral(axes: Tensor, sharpness: Tensor, lobe: Tensor, lobe_sharpness: Tensor) -> Tensor:
    """int exp(l_k (v . xi_k - 1)) exp(l_r (v . d - 1)) dv for lobes [K, 3], [K] and directions [P, 3] unit with
    their sharpness [P] -> [P, K]: 2 pi e^(m - L) (1 - e^-2m) / m with m = |l_k xi_k + l_r d|, L = l_k + l_r; m - L is
    formed as 2 l_k l_r (xi . d - 1) / (m + L), free of the cancellation of two large numbers."""
    lk, lr = sharpness[None, :], lobe_sharpness[:, None]  # [1, K], [P, 1]
    cos = lobe @ axes.T  # [P, K]
    m = (lk.square() + lr.square() + 2 * lk * lr * cos).clamp_min(1e-12).sqrt()
    return 2 * math.pi * torch.exp(2 * lk * lr * (cos - 1.0) / (m + lk + lr)) * -torch.expm1(-2 * m) / m


def _azimuth_integral(a: Tensor, b: Tensor) -> Tensor:  # [...] x2 (b >= 0) -> [...] int_0^2pi max(a + b cos p, 0) dp
    inside = (-a / b.clamp_min(1e-300)).clamp(-1.0, 1.0)
    partial = 2 * (a * torch.arccos(inside) + (b.square() - a.square()).clamp_min(0.0).sqrt())
    return torch.where(a >= b, 2 * math.pi * a, torch.where(a <= -b, torch.zeros_like(a), partial))


def cosine_integral(sharpness: Tensor, cos: Tensor, nodes: int = 1024) -> Tensor:  # [S], [C] -> [S, C] float64
    """int exp(lambda (v . xi - 1)) (n . v)+ dv with n . xi = cos, over the angle from the axis: with t = lambda
    (1 - v . xi), lambda^-1 int_0^{2 lambda} e^-t h(1 - t / lambda) dt, h the azimuth's closed form; midpoint rule on
    t in [0, min(2 lambda, 40)] (e^-40 is far below float precision)."""
    lam = sharpness.double()[:, None, None]  # [S, 1, 1]
    span = torch.clamp(2 * lam, max=40.0)
    t = (torch.arange(nodes, dtype=torch.float64) + 0.5)[None, None, :] / nodes * span  # [S, 1, T]
    u = (1.0 - t / lam).clamp(-1.0, 1.0)
    c = cos.double()[None, :, None]  # [1, C, 1]
    h = _azimuth_integral(u * c, ((1 - u.square()).clamp_min(0) * (1 - c.square()).clamp_min(0)).sqrt())
    return (torch.exp(-t) * h).sum(-1) * (span[..., 0] / nodes) / lam[..., 0]


def cosine_table(device, dtype) -> Tensor:  # -> [1, 1, C, S]: rows n . xi from -1 to 1, columns log lambda
    """`cosine_integral` over `sg_integral` (a weighted mean of (n . v)+, in [0, 1]) on the table's grid (cached)."""
    key = (str(device), dtype)
    if key not in _TABLES:
        if "table" not in _TABLES:  # made once, in float64 on the CPU
            low, high = (math.log(x) for x in TABLE_SHARPNESS)
            sharpness = torch.linspace(low, high, TABLE_SIZE[0], dtype=torch.float64).exp()
            cos = torch.linspace(-1.0, 1.0, TABLE_SIZE[1], dtype=torch.float64)
            _TABLES["table"] = (cosine_integral(sharpness, cos) / sg_integral(sharpness)[:, None]).T[None, None]
        _TABLES[key] = _TABLES["table"].to(device=device, dtype=dtype)  # [1, 1, C, S]
    return _TABLES[key]


def sg_irradiance(axes: Tensor, sharpness: Tensor, amplitudes: Tensor, normals: Tensor, table: Tensor) -> Tensor:
    """[K, 3] unit, [K], [K, 3], [P, 3] unit, `cosine_table` -> [P, 3] E(n) = sum_k mu_k int SG_k(v) (n . v)+ dv."""
    low, high = (math.log(x) for x in TABLE_SHARPNESS)
    column = (sharpness.log() - low) * (2.0 / (high - low)) - 1.0  # [K] grid_sample's x (align_corners=True)
    row = normals @ axes.T  # [P, K] n . xi is already in [-1, 1]
    grid = torch.stack([column.expand_as(row), row], dim=-1)[None]  # [1, P, K, 2]
    mean_cosine = F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, 0]
    return (mean_cosine * sg_integral(sharpness)) @ amplitudes  # [P, K] @ [K, 3]


def level_lobes(levels: tuple[float, ...], device, dtype) -> Tensor:  # -> [L] log `lobe_sharpness` per level
    key = ("lobes", levels, str(device), dtype)
    if key not in _TABLES:
        _TABLES[key] = torch.tensor([math.log(lobe_sharpness(r)) for r in levels], dtype=dtype, device=device)
    return _TABLES[key]


def lobe_sharpness(roughness: float) -> float:
    """The sharpness of the SG with the mean cosine to its axis of the split-sum lobe D V (r.l)+ (n = v = r) of this
    roughness: that mean by quadrature over the angle, then coth(l) - 1 / l = mean solved by bisection in log l."""
    alpha = torch.tensor(level_alpha(roughness), dtype=torch.float64)
    theta = (torch.arange(20000, dtype=torch.float64) + 0.5) * (math.pi / 2 / 20000)  # (r.l)+ ends at pi / 2
    cos = torch.cos(theta)
    n_dot_h = torch.sqrt((1.0 + cos) / 2.0)
    weights = ggx_ndf(n_dot_h, alpha) * smith_visibility(cos, torch.ones_like(cos), alpha) * cos * torch.sin(theta)
    mean = float((weights * cos).sum() / weights.sum())
    low, high = math.log(1e-3), math.log(1e8)
    for _ in range(200):
        mid = (low + high) / 2
        lam = math.exp(mid)
        low, high = (mid, high) if 1 / math.tanh(lam) - 1 / lam < mean else (low, mid)
    return math.exp((low + high) / 2)


# ------------------------------------------------------------------------------------------ prefiltered
@dataclass
class PrefilteredSG(PrefilteredLight):
    """An SG light as split-sum shading reads it: its lobes and the lobe sharpness of each roughness level."""

    levels: tuple[float, ...]
    height: int  # rows of `source`
    axes: Tensor  # [K, 3] unit
    sharpness: Tensor  # [K]
    amplitudes: Tensor  # [K, 3]
    log_lobe_sharpness: Tensor  # [L] log of `lobe_sharpness` of each level
    table: Tensor  # [1, 1, C, S] `cosine_table`: a constant, but an input of a captured graph like the rest
    source: Tensor | None = None  # [h, 2h, 3] the light drawn on a lat-long grid

    @property
    def layout(self) -> tuple:
        return self.levels, self.height

    def tensors(self) -> tuple[Tensor, ...]:
        return self.axes, self.sharpness, self.amplitudes, self.log_lobe_sharpness, self.table

    @classmethod
    def from_tensors(cls, layout: tuple, tensors) -> PrefilteredSG:
        return cls(*layout, *tensors)

    def lookup_specular(self, directions: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
        d = F.normalize(directions.reshape(-1, 3).to(self.axes.dtype), dim=-1, eps=1e-12)
        if len(self.levels) == 1:
            lobe = self.log_lobe_sharpness.exp().expand(len(d))
        else:  # log-linear between the levels
            weights = _level_weights(roughness.to(d.dtype).reshape(-1), self.levels)  # [L, P]
            lobe = (weights * self.log_lobe_sharpness[:, None]).sum(0).exp()  # [P]
        products = sg_product_integral(self.axes, self.sharpness, d, lobe) / sg_integral(lobe)[:, None]  # [P, K]
        return (products @ self.amplitudes).reshape(*directions.shape[:-1], 3)

    def lookup_diffuse(self, normals: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        n = F.normalize(normals.reshape(-1, 3).to(self.axes.dtype), dim=-1, eps=1e-12)
        irradiance = sg_irradiance(self.axes, self.sharpness, self.amplitudes, n, self.table)  # [P, 3]
        return irradiance.reshape(*normals.shape[:-1], 3)


def sg_step(
    layout: tuple, vectors: Tensor, log_sharpness: Tensor, log_amplitudes: Tensor, lobes: Tensor, table: Tensor
) -> tuple[Tensor, ...]:  # [K, 3], [K], [K, 3], [L] (`level_lobes`), `cosine_table` ->
    """A learnable SG light's prefiltering step (`Light.step_function`): the `PrefilteredSG` tensors, the light drawn
    on a lat-long grid [h, 2h, 3] and its prior []; one pure function of the parameters, for a CUDA graph."""
    _, height = layout
    axes, sharpness, amplitudes = F.normalize(vectors, dim=-1), log_sharpness.exp(), log_amplitudes.exp()
    grid = pixel_directions(height, 2 * height, vectors.device, vectors.dtype)  # [h, 2h, 3]
    drawn = sg_radiance(axes, sharpness, amplitudes, grid)
    prior = total_variation(drawn.clamp_min(MIN_RADIANCE).log())
    return axes, sharpness, amplitudes, lobes, table, drawn, prior


def fibonacci_axes(count: int, dtype=torch.float32, device=None) -> Tensor:  # -> [count, 3] unit, evenly spread
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    rho = (1.0 - z.square()).sqrt()
    return torch.stack([rho * phi.cos(), rho * phi.sin(), z], dim=-1).to(device=device, dtype=dtype)


# ------------------------------------------------------------------------------------------ the module
class SGLight(Light):
    """A mixture of K spherical Gaussians (see the module's text); `height`: rows of its lat-long drawing."""

    kind = "sg"
    prefiltered_type = PrefilteredSG

    def __init__(self, axes: Tensor, sharpness: Tensor, amplitudes: Tensor, height: int, learnable: bool = True):
        super().__init__()
        self.vectors = nn.Parameter(F.normalize(axes.detach(), dim=-1).clone(), requires_grad=learnable)  # [K, 3]
        self.log_sharpness = nn.Parameter(sharpness.detach().log().clone(), requires_grad=learnable)  # [K]
        self.log_amplitudes = nn.Parameter(amplitudes.detach().clamp_min(MIN_RADIANCE).log(), requires_grad=learnable)
        self.height = int(height)

    @classmethod
    def initial(cls, value: float, height: int, device=None) -> SGLight:
        """LOBES_PER_ROW x `height` lobes spread evenly, each about as wide as the spacing between them, with the
        amplitude that gives a mean radiance `value`."""
        count = LOBES_PER_ROW * height
        sharpness = torch.full((count,), count / (2 * math.pi), device=device)
        amplitude = 4 * math.pi * value / (count * sg_integral(sharpness[:1]))
        return cls(fibonacci_axes(count, device=device), sharpness, amplitude.expand(count, 3), height)

    @property
    def lobes(self) -> tuple[Tensor, Tensor, Tensor]:  # axes [K, 3] unit, sharpness [K], amplitudes [K, 3]
        return F.normalize(self.vectors, dim=-1), self.log_sharpness.exp(), self.log_amplitudes.exp()

    @property
    def map(self) -> Tensor:  # [h, 2h, 3]
        return self.radiance(pixel_directions(self.height, 2 * self.height, self.vectors.device, self.vectors.dtype))

    def radiance(self, directions: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
        return sg_radiance(*self.lobes, directions.to(self.vectors.dtype))

    def step_function(self, levels):
        levels = tuple(float(r) for r in levels)
        device, dtype = self.vectors.device, self.vectors.dtype
        constants = level_lobes(levels, device, dtype), cosine_table(device, dtype)  # made outside any graph
        return sg_step, (levels, self.height), (self.vectors, self.log_sharpness, self.log_amplitudes, *constants)

    def prefilter(self, levels=DEFAULT_LEVELS) -> PrefilteredSG:
        function, layout, tensors = self.step_function(levels)
        *parts, drawn, _ = function(layout, *tensors)
        return PrefilteredSG(*layout, *parts, source=drawn)

    def prior(self) -> Tensor:
        return total_variation(self.map.clamp_min(MIN_RADIANCE).log())

    def fixed(self) -> SGLight:
        fixed = copy.deepcopy(self)  # the parameters as they are (not through exp and log again)
        fixed.requires_grad_(False)
        return fixed

    def save(self, path) -> None:
        write_image(path, self.map.detach())
        axes, sharpness, amplitudes = (t.detach().cpu().double().tolist() for t in self.lobes)
        lobes = {"model": self.kind, "height": self.height, "axes": axes, "sharpness": sharpness}
        write_json(lobes_path(path), {**lobes, "amplitudes": amplitudes})

    @classmethod
    def saved_at(cls, path) -> bool:
        return lobes_path(path).is_file()

    @classmethod
    def load(cls, path) -> SGLight:
        where = lobes_path(path)
        data = read_record(where, "write it with SGLight.save")
        try:
            axes, sharpness, amplitudes = (torch.tensor(data[k]) for k in ("axes", "sharpness", "amplitudes"))
            count, height = len(axes), int(data["height"])
            shapes_ok = axes.shape == (count, 3) and sharpness.shape == (count,) and amplitudes.shape == (count, 3)
        except (KeyError, TypeError, ValueError, RuntimeError):
            shapes_ok = False
        if not shapes_ok or count == 0 or height < 1 or not bool((sharpness > 0).all() and (amplitudes >= 0).all()):
            raise file_error(
                where,
                "is not a spherical-Gaussian light (K axes [K, 3], sharpness [K] > 0, amplitudes [K, 3] >= 0, height)",
                "write it with SGLight.save",
            )
        return cls(axes.float(), sharpness.float(), amplitudes.float(), height, learnable=False)


def lobes_path(path) -> Path:  # envmap.exr -> envmap.sg.json
    path = Path(path)
    return path.with_name(f"{path.stem}.sg.json")
