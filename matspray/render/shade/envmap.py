"""A learnable lat-long HDR environment map and its split-sum prefiltering.

Maps follow `matspray.render.shade.latlong`: [H, 2H, 3] linear RGB, world up +z, row 0 straight up.

`EnvironmentMap` holds the map as the log of the radiance (`log_map`), so it stays positive and an
optimiser step changes it multiplicatively, which suits HDR values spanning orders of magnitude.

`prefilter_latlong(map, levels)` turns a map into what split-sum shading reads:
- specular: for each roughness level, the map convolved with the specular lobe under the n = v = r
  assumption: L_r(r) = sum_l L(l) w(l) dw_l / sum_l w(l) dw_l with w = D(h) V(r.l, 1) (r.l)+ and
  h = normalize(r + l). Including V (Karis weights by D (r.l) only) makes the split-sum exact for a
  surface seen head-on up to Fresnel's variation, and measurably closer elsewhere;
- diffuse: the irradiance E(n) = sum_l L(l) (n.l)+ dw_l (the cosine convolution).
Both are exact sums over the input pixels with their solid angles. A lat-long map is symmetric under
rotation about the up axis, so the weight between an output pixel and an input pixel depends only on
the two rows and the column offset; each sum is therefore a circular correlation along the rows,
done with FFTs and one small complex matrix product per frequency against a precomputed kernel
[W_in // 2 + 1, H_out, H_in] (cached per size). It is differentiable w.r.t. the map and costs
O(H_out H_in W) per level. Rough levels (and the irradiance) are evaluated on coarser output
grids (H_in / 2^k rows), always from the full input.

Refinement prefilters its learnable map every step, so `prefilter_latlong` makes every level and the irradiance
at once: their kernels stacked into one (one FFT, one product per frequency, one inverse FFT for all), with rows
that lay each map out ready for bilinear lookup (`_padded_rows`); `PrefilteredEnvironment` looks the levels of one
resolution up together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matspray.data.images import read_image, write_image
from matspray.errors import ConfigError, DataError, file_error
from matspray.render.shade.bilinear import bilinear_sample, grid_sample_border
from matspray.render.shade.brdf import MIN_ROUGHNESS, ggx_ndf, roughness_to_alpha, smith_visibility
from matspray.render.shade.latlong import pixel_solid_angles, total_variation
from matspray.render.shade.light import Light, PrefilteredLight
from matspray.render.shade.lights import physical_radiance

DEFAULT_LEVELS = (MIN_ROUGHNESS, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
PIXELS_PER_LOBE = 2.0  # a level's pixel spans at most alpha / PIXELS_PER_LOBE radians (the GGX lobe ~ alpha wide)
MIN_LEVEL_HEIGHT = 16
DIFFUSE_HEIGHT = 16  # irradiance is a cosine-weighted integral of the light, smooth: a coarse map holds it
MIN_RADIANCE = 1e-4  # floor applied to maps before taking the log

_KERNELS: dict[tuple, Tensor] = {}  # prefiltering's kernels
_RUNS: dict[tuple, list] = {}  # how the stacked kernel's rows make maps (`_prefilter_kernel`)
_CONSTANTS: dict[tuple, Tensor] = {}  # small per-size constants of the lookups


# ------------------------------------------------------------------------------------------ validation
def check_latlong(map: Tensor, what: str = "environment map") -> None:
    """Raise DataError unless `map` is a finite, non-negative [H, 2H, 3] tensor."""
    shape = tuple(map.shape)
    if map.ndim != 3 or shape[-1] != 3 or shape[1] != 2 * shape[0] or shape[0] < 1:
        raise DataError(
            f"{what} must be lat-long with width = 2 x height and 3 channels ([H, 2H, 3]), got shape {list(shape)} "
            "(convert it to an equirectangular map, e.g. 1024 x 2048)"
        )
    if not torch.isfinite(map).all():
        raise DataError(f"{what} holds NaN or Inf values")
    if (map < 0).any():
        raise DataError(
            f"{what} holds negative radiance (min {float(map.min()):.3g}); environment maps are linear and >= 0"
        )


# ------------------------------------------------------------------------------------------ resampling
def downsample_latlong(map: Tensor, height: int) -> Tensor:  # [H, 2H, C] -> [height, 2 height, C]
    """Solid-angle weighted area average onto a coarser lat-long grid (keeps the total power)."""
    if map.shape[0] <= height:
        return map
    weights = pixel_solid_angles(map.shape[0], map.shape[1], device=map.device, dtype=map.dtype)[..., None]
    size = (height, 2 * height)
    num = F.adaptive_avg_pool2d((map * weights).permute(2, 0, 1), size)
    den = F.adaptive_avg_pool2d(weights.permute(2, 0, 1), size)
    return (num / den).permute(1, 2, 0)


def latlong_angles(d: Tensor) -> Tensor:  # [..., 3] -> [..., 2] azimuth, polar angle
    """The lat-long angles of directions (any length > 0: the angles do not depend on it): phi = atan2(y, -x) in
    [-pi, pi] (u = phi / 2 pi + 0.5, see `latlong.direction_to_uv`) and theta = atan2(|(x, y)|, z) in [0, pi]
    (v = theta / pi), which equals acos(z) for unit d but stays accurate and differentiable next to the poles."""
    x, y, z = d.unbind(-1)
    rho = torch.linalg.vector_norm(d[..., :2], dim=-1)  # its gradient is 0 at rho = 0
    at_pole = rho < 1e-12  # azimuth undefined: a fixed one (phi = 0), with no gradient
    # both angles by one atan2: [..., 2] numerators over denominators
    numerators = torch.stack([torch.where(at_pole, 0.0, y), rho], dim=-1)
    return torch.atan2(numerators, torch.stack([torch.where(at_pole, 1.0, -x), z], dim=-1))


def sample_padded(image: Tensor, grid: Tensor) -> Tensor:  # [1, C, h, w], [P, 2] -> [C, P]
    """Bilinear samples of a padded map at `grid_sample` coordinates (align_corners=True). On a GPU by
    `bilinear_sample`, whose backward does not queue a view's pixels on the map's few texels."""
    if image.is_cuda and torch.is_grad_enabled():
        return bilinear_sample(image, grid)
    return grid_sample_border(image, grid)


def sample_latlong(map: Tensor, directions: Tensor) -> Tensor:  # [H, W, C], [..., 3] -> [..., C]
    """Bilinear lookup in a lat-long map along directions (any length > 0), wrapping around in azimuth.

    Between the first (last) row of pixel centres and the pole, values blend towards the pole's
    radiance, estimated as the mean of that row; so the lookup is continuous across the poles.
    """
    height, width, channels = map.shape
    wrapped = torch.cat([map[:, -1:], map, map[:, :1]], dim=1)  # [H, W + 2, C]
    poles = torch.stack([map[0].mean(0), map[-1].mean(0)])[:, None].expand(2, width + 2, channels)
    padded = torch.cat([poles[:1], wrapped, poles[1:]])  # [H + 2, W + 2, C]; pixel (i, j) sits at (i + 1, j + 1)
    phi, theta = latlong_angles(directions.to(map.dtype).reshape(-1, 3)).unbind(-1)
    x = phi * (width / (math.pi * (width + 1)))  # column u W + 0.5 (u = phi / 2 pi + 0.5) / (W + 1) * 2 - 1
    t = theta * (height / math.pi)  # v H: the map's row coordinate + 0.5
    inside = (t - 0.5).clamp(0.0, height - 1)  # the row coordinate, held at the outer centres
    # the poles lie half a row beyond the outer centres: padded row 2 t - inside (t + 0.5 between the outer
    # centres, twice as steep beyond them), / (H + 1) * 2 - 1
    y = torch.sub(t, inside, alpha=0.5) * (4.0 / (height + 1)) - 1.0
    samples = sample_padded(padded.permute(2, 0, 1)[None], torch.stack([x, y], dim=-1))  # [C, P]
    return samples.T.reshape(*directions.shape[:-1], channels)


def latlong_grids(angles: Tensor, widths) -> dict[int, Tensor]:  # [..., 2] (`latlong_angles`) -> {W: [..., 2]}
    """`grid_sample` coordinates (align_corners=True) of the angles in prefiltered maps of each width W, padded as
    `_padded_rows` lays them out: column u W + 0.5 of the W + 2 (u = phi / 2 pi + 0.5), row v 2H of the 2H + 1 (the
    same for every map)."""
    grids = {}
    for width in widths:
        key = ("grid", width, angles.dtype, str(angles.device))
        if key not in _CONSTANTS:
            # column (u W + 0.5) / (W + 1) * 2 - 1 = phi W / (pi (W + 1)); row v 2H / 2H * 2 - 1 = theta 2 / pi - 1
            scale = [width / (math.pi * (width + 1)), 2.0 / math.pi]
            _CONSTANTS[key] = torch.tensor([scale, [0.0, -1.0]], dtype=angles.dtype, device=angles.device)  # [2, 2]
        scale, offset = _CONSTANTS[key]
        grids[width] = angles * scale + offset
    return grids


# ------------------------------------------------------------------------------------------ prefiltering
def _coarsest_height(map_height: int, at_least: float) -> int:
    """The smallest map_height / 2^k that is still >= at_least (so output pixels tile input pixels)."""
    height = map_height
    while height % 2 == 0 and height // 2 >= at_least:
        height //= 2
    return height


def level_height(roughness: float, map_height: int, min_height: int = MIN_LEVEL_HEIGHT) -> int:
    """Rows of the prefiltered map for one roughness: as coarse as the GGX lobe's width allows."""
    alpha = max(roughness, MIN_ROUGHNESS) ** 2
    return _coarsest_height(map_height, max(PIXELS_PER_LOBE * math.pi / alpha, min_height))


def _lobe_weights(kind: str, alpha: float, in_height: int, out_height: int) -> Tensor:  # -> [H_out, H_in, W_in]
    """The weights (float64, on the CPU) between an output pixel of column 0 and every input pixel, 'ggx' (the lobe
    D V (r.l)+, normalised to sum to 1) or 'cosine' ((n.l)+, summing to pi)."""
    host = torch.device("cpu")
    in_width, stride = 2 * in_height, in_height // out_height
    theta_in = (torch.arange(in_height, dtype=torch.float64, device=host) + 0.5) / in_height * math.pi
    theta_out = (torch.arange(out_height, dtype=torch.float64, device=host) + 0.5) / out_height * math.pi
    # azimuth of input column m relative to output column 0 (output pixels are `stride` input pixels wide)
    dphi = (torch.arange(in_width, dtype=torch.float64, device=host) + 0.5 - stride / 2) * (2 * math.pi / in_width)
    cos = torch.cos(theta_out)[:, None, None] * torch.cos(theta_in)[None, :, None] + torch.sin(theta_out)[
        :, None, None
    ] * torch.sin(theta_in)[None, :, None] * torch.cos(dphi)  # [H_out, H_in, W_in]
    solid_angle = pixel_solid_angles(in_height, in_width, device=host, dtype=torch.float64)[:, :1]  # [H_in, 1]
    weights = cos.clamp_min(0.0) * solid_angle
    if kind == "ggx":  # the specular lobe D V (n.l) of a surface seen head-on: n = v = r
        a = torch.tensor(alpha, dtype=torch.float64, device=host)
        n_dot_h = torch.sqrt(((1.0 + cos) / 2.0).clamp_min(0.0))
        weights = weights * ggx_ndf(n_dot_h, a) * smith_visibility(cos, torch.ones_like(cos), a)
        return weights / weights.sum(dim=(1, 2), keepdim=True)
    # the exact integral of (n.l)+ is pi: remove the sum's small discretisation error
    return weights * (math.pi / weights.sum(dim=(1, 2), keepdim=True))


def _complex(dtype: torch.dtype) -> torch.dtype:
    return torch.complex128 if dtype == torch.float64 else torch.complex64


def _kernel_spectrum(kind: str, alpha: float, in_height: int, out_height: int, device, dtype) -> Tensor:
    """`_lobe_weights` as their conjugated rfft along azimuth, laid out [2 in_height // 2 + 1, out_height,
    in_height], on `device` (cached per size)."""
    key = (kind, alpha, in_height, out_height, str(device), dtype)
    if key not in _KERNELS:  # made once on the CPU in float64, then kept on `device`
        weights = _lobe_weights(kind, alpha, in_height, out_height)
        spectrum = torch.fft.rfft(weights, dim=-1).conj().permute(2, 0, 1)  # [F, H_out, H_in], ready to matmul
        _KERNELS[key] = spectrum.to(device=device, dtype=_complex(dtype)).contiguous()
    return _KERNELS[key]


def _correlate(map: Tensor, spectrum: Tensor) -> Tensor:  # [H_in, W_in, C], [F, H_out, H_in] -> [H_out, 2 H_out, C]
    """out[a, j] = sum_{b, m} w[a, b, m] map[b, stride * j + m]  (circular in the column index): per
    frequency f, out^[f] = conj(w^[f]) @ map^[f] (the kernel is stored conjugated)."""
    in_width, out_height = map.shape[1], spectrum.shape[1]
    map_spectrum = torch.fft.rfft(map, dim=1).permute(1, 0, 2)  # [F, H_in, C]
    out = torch.matmul(spectrum, map_spectrum).permute(1, 0, 2)  # [H_out, F, C]
    out = torch.fft.irfft(out, n=in_width, dim=1)  # [H_out, W_in, C]
    return out[:, :: in_width // (2 * out_height)]


def level_alpha(roughness: float) -> float:
    """The GGX alpha of a prefiltered level, as a host-side number (float32 rounding, as shading's)."""
    return float(roughness_to_alpha(torch.tensor(roughness, device="cpu")))


def prefilter_specular(map: Tensor, roughness: float) -> Tensor:  # [H, 2H, 3] -> [h, 2h, 3]
    height = level_height(roughness, map.shape[0])
    return _correlate(map, _kernel_spectrum("ggx", level_alpha(roughness), map.shape[0], height, map.device, map.dtype))


def irradiance_map(map: Tensor, height: int = DIFFUSE_HEIGHT) -> Tensor:  # [H, 2H, 3] -> [h, 2h, 3]
    """E(n) = integral L(l) (n.l)+ dl at the pixel centres of a coarse lat-long grid."""
    out_height = _coarsest_height(map.shape[0], height)
    return _correlate(map, _kernel_spectrum("cosine", 0.0, map.shape[0], out_height, map.device, map.dtype))


@dataclass(frozen=True)
class _Run:
    """Prefiltered maps of one resolution, made together: rows [start, stop) of the stacked kernel's output."""

    start: int
    stop: int
    count: int  # maps
    height: int  # rows of each map (unpadded)
    columns: Tensor  # [2 height + 2] input columns of the padded output columns (stride, wrapped round)


def _padded_rows(weights: Tensor) -> Tensor:  # [h, H_in, W_in] -> [2h + 1, H_in, W_in]
    """A level's weights as the rows of its map padded for lookup, rows at v = k / 2h, k = 0 .. 2h: pixel row i at
    k = 2i + 1, the mean of two neighbouring pixel rows between them, and at k = 0 (2h) a row whose output, in every
    column, is the mean of the first (last) pixel row over its 2h columns: the pole's radiance. Bilinear lookup in
    these rows is bilinear between the pixel centres, blends towards the pole's radiance beyond the outer ones (as
    `sample_latlong`), and its row coordinate v 2h is linear in v."""
    height, in_height, in_width = weights.shape
    stride = in_width // (2 * height)
    # output column j' of a row with weights w' is sum w'[b, m] map[b, stride j' + m]; averaging the row's weights
    # over all shifts by stride makes it the mean over the output columns, the same in every column
    poles = [sum(row.roll(stride * j, dims=-1) for j in range(2 * height)) / (2 * height) for row in weights[[0, -1]]]
    between = (weights[:-1] + weights[1:]) / 2
    rows = torch.stack([weights[:-1], between], dim=1).reshape(2 * height - 2, in_height, in_width)
    return torch.cat([poles[0][None], rows, weights[-1:], poles[1][None]])


def _prefilter_kernel(levels: tuple[float, ...], in_height: int, device, dtype) -> tuple[Tensor, list[_Run]]:
    """Every specular level's kernel and the irradiance's, stacked into one matrix [F, H_in, R] (conjugated rfft
    along azimuth, transposed so that map^T @ kernel gives all R output rows at once), and the runs of maps of one
    resolution in row order: consecutive specular levels of one height, then the irradiance. Each map has the 2h + 1
    `_padded_rows`, and within a run map i's rows follow map i - 1's (cached per size)."""
    key = ("stacked", levels, in_height, str(device), dtype)
    if key not in _KERNELS or key not in _RUNS:
        maps = [(level_height(r, in_height), "ggx", level_alpha(r)) for r in levels]
        maps.append((_coarsest_height(in_height, DIFFUSE_HEIGHT), "cosine", 0.0))
        blocks, runs, start = [], [], 0
        for i, (height, kind, alpha) in enumerate(maps):
            blocks.append(_padded_rows(_lobe_weights(kind, alpha, in_height, height)))
            rows = 2 * height + 1
            if 0 < i < len(levels) and runs[-1].height == height:  # a specular level joins the previous one's run
                runs[-1] = replace(runs[-1], stop=runs[-1].stop + rows, count=runs[-1].count + 1)
            else:
                stride = in_height // height
                columns = (torch.arange(-1, 2 * height + 1, device=device) * stride) % (2 * in_height)
                runs.append(_Run(start, start + rows, 1, height, columns))
            start += rows
        spectrum = torch.fft.rfft(torch.cat(blocks), dim=-1).conj().permute(2, 1, 0)  # [F, H_in, R]
        _KERNELS[key] = spectrum.to(device=device, dtype=_complex(dtype)).contiguous()
        _RUNS[key] = runs
    return _KERNELS[key], _RUNS[key]


def _level_weights(roughness: Tensor, levels: tuple[float, ...]) -> Tensor:  # [P] -> [L, P]
    """Linear interpolation weights between roughness levels (clamped to their range): for r between levels i and
    i + 1, (l_{i+1} - r) / (l_{i+1} - l_i) on level i and (r - l_i) / (l_{i+1} - l_i) on level i + 1, 0 elsewhere.
    Each level's weight is the smaller of its two ramps (the outer levels' outward ramps never bind), clamped at 0."""
    key = ("level ramps", levels, str(roughness.device), roughness.dtype)
    if key not in _CONSTANTS:
        at = torch.tensor(levels, dtype=roughness.dtype, device=roughness.device)  # as shading's dtype rounds them
        below = torch.cat([at[:1] - 1.0, at[:-1]])  # the previous level (one below the first: a ramp above 1)
        above = torch.cat([at[1:], at[-1:] + 1.0])
        _CONSTANTS[key] = torch.stack([below, at - below, above, above - at])[..., None]  # [4, L, 1]
    below, rise, above, fall = _CONSTANTS[key]
    r = roughness.clamp(levels[0], levels[-1])
    return torch.minimum((r - below) / rise, (above - r) / fall).clamp_min(0.0)


@dataclass
class PrefilteredEnvironment(PrefilteredLight):
    """What split-sum shading reads from an environment: prefiltered specular levels and irradiance, kept as padded
    images for bilinear lookup (rows as `_padded_rows`, columns wrapped round by one on each side): levels of one
    resolution together, as channels."""

    levels: tuple[float, ...]  # L roughness levels, increasing
    specular_images: list[Tensor]  # runs of levels of one resolution h: [1, 3 k, 2h + 1, 2h + 2], channel c k + i
    # holding channel c of the run's level i
    irradiance_image: Tensor  # [1, 3, 2h + 1, 2h + 2]
    source: Tensor | None = None  # [H, 2H, 3] the map it was prefiltered from (for `render.visibility`)

    @property
    def layout(self) -> tuple[float, ...]:
        return self.levels

    def tensors(self) -> tuple[Tensor, ...]:
        """The specular runs' images, then the irradiance's (what a captured graph takes)."""
        return (*self.specular_images, self.irradiance_image)

    @classmethod
    def from_tensors(cls, layout: tuple[float, ...], tensors) -> PrefilteredEnvironment:
        return cls(layout, list(tensors[:-1]), tensors[-1])

    @property
    def roughness_levels(self) -> Tensor:  # [L]
        return torch.tensor(self.levels, dtype=self.irradiance_image.dtype, device=self.irradiance_image.device)

    @property
    def specular(self) -> list[Tensor]:  # L maps [h_i, 2 h_i, 3]
        maps = []
        for image in self.specular_images:
            inner = image[0, :, 1:-1:2, 1:-1]  # [3 k, h, 2h] the pixel rows and columns
            maps += inner.reshape(3, -1, *inner.shape[1:]).permute(1, 2, 3, 0).unbind(0)
        return maps

    @property
    def irradiance(self) -> Tensor:  # [h, 2h, 3]
        return self.irradiance_image[0, :, 1:-1:2, 1:-1].permute(1, 2, 0)

    def lookup(self, directions: Tensor, roughness: Tensor, normals: Tensor) -> tuple[Tensor, Tensor]:
        """`lookup_specular(directions, roughness)` and `lookup_diffuse(normals)` [..., 3] each, for directions,
        roughness and normals of one shape [..., 3], [...], [..., 3], sharing their angles' arithmetic."""
        count = roughness.numel()
        both = torch.cat([directions.reshape(-1, 3), normals.reshape(-1, 3)]).to(self.irradiance_image.dtype)
        grids = self._grids(latlong_angles(both))  # {W: [2P, 2]}
        width = self.irradiance_image.shape[-1] - 2
        diffuse = sample_padded(self.irradiance_image, grids[width][count:])  # [3, P]
        specular = self._specular(roughness, {w: grid[:count] for w, grid in grids.items()})
        return specular.T.reshape(*directions.shape), diffuse.T.reshape(*normals.shape)

    def lookup_specular(self, directions: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
        """Prefiltered radiance around reflection directions (any length > 0), linear between roughness levels."""
        grids = self._grids(latlong_angles(directions.to(self.irradiance_image.dtype).reshape(-1, 3)))
        return self._specular(roughness, grids).T.reshape(*directions.shape[:-1], 3)

    def lookup_diffuse(self, normals: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        """Irradiance E(n) = integral L(l) (n.l)+ dl; Lambert radiance is albedo / pi times this."""
        grids = self._grids(latlong_angles(normals.to(self.irradiance_image.dtype).reshape(-1, 3)))
        samples = sample_padded(self.irradiance_image, grids[self.irradiance_image.shape[-1] - 2])
        return samples.T.reshape(*normals.shape[:-1], 3)

    def _grids(self, angles: Tensor) -> dict[int, Tensor]:  # [P, 2] -> {W: [P, 2]} for every image
        widths = {image.shape[-1] - 2 for image in [*self.specular_images, self.irradiance_image]}
        return latlong_grids(angles, sorted(widths))

    def _specular(self, roughness: Tensor, grids: dict[int, Tensor]) -> Tensor:  # [...], {W: [P, 2]} -> [3, P]
        samples = [
            sample_padded(image, grids[image.shape[-1] - 2]).view(3, -1, roughness.numel())
            for image in self.specular_images
        ]  # [3, k, P] per run
        samples = torch.cat(samples, dim=1) if len(samples) > 1 else samples[0]  # [3, L, P]
        if len(self.levels) == 1:
            return samples[:, 0]
        weights = _level_weights(roughness.to(samples.dtype).reshape(-1), self.levels)  # [L, P]
        return (samples * weights).sum(1)


def prefilter_latlong(map: Tensor, levels=DEFAULT_LEVELS) -> PrefilteredEnvironment:  # map [H, 2H, 3]
    """Every level and the irradiance by one correlation (`_prefilter_kernel`): one FFT of the map, one matrix
    product per frequency and one inverse FFT, then each run's columns (stride, wrapped round) in one gather."""
    levels = tuple(float(r) for r in levels)
    if not levels or any(b <= a for a, b in zip(levels, levels[1:])) or levels[0] < 0 or levels[-1] > 1:
        raise ConfigError(f"roughness levels must be strictly increasing values in [0, 1], got {list(levels)}")
    kernel, runs = _prefilter_kernel(levels, map.shape[0], map.device, map.dtype)
    channels, in_width = map.shape[2], map.shape[1]
    spectrum = torch.fft.rfft(map, dim=1).permute(1, 2, 0)  # [F, C, H_in]
    rows = torch.fft.irfft(torch.matmul(spectrum, kernel).permute(1, 2, 0), n=in_width, dim=-1)  # [C, R, W_in]
    images = [
        rows[:, run.start : run.stop]
        .index_select(2, run.columns)
        .view(1, channels * run.count, 2 * run.height + 1, 2 * run.height + 2)
        for run in runs
    ]
    return PrefilteredEnvironment(levels, images[:-1], images[-1], source=map)


def prefilter_log_map(levels: tuple[float, ...], log_map: Tensor) -> tuple[Tensor, ...]:  # [h, 2h, 3] ->
    """A learnable map's split-sum images (`PrefilteredEnvironment.tensors` of `prefilter_latlong`), its linear map
    [h, 2h, 3] (what shadowing reads) and the total variation of its log radiance [] (the light prior): one pure
    function of the map, for a CUDA graph."""
    radiance = log_map.exp()
    return (*prefilter_latlong(radiance, levels).tensors(), radiance, total_variation(log_map))


# ------------------------------------------------------------------------------------------ the module
class EnvironmentMap(Light):
    """A lat-long HDR environment light [H, 2H, 3], stored as log radiance so that it stays positive."""

    kind = "latlong"
    prefiltered_type = PrefilteredEnvironment

    def __init__(self, log_map: Tensor, learnable: bool = True):
        super().__init__()
        check_latlong(log_map.exp().detach(), "environment map")
        self.log_map = nn.Parameter(log_map.detach().clone(), requires_grad=learnable)

    @classmethod
    def from_tensor(cls, map: Tensor, height: int | None = None, learnable: bool = True, what: str = "environment map"):
        """From linear radiance [H, 2H, 3] (area-downsampled to at most `height` rows); values are
        floored at MIN_RADIANCE before taking the log."""
        check_latlong(map, what)
        map = map if map.is_floating_point() else map.float()
        if height is not None:
            if height < 1:
                raise ConfigError(f"environment map height must be >= 1, got {height}")
            map = downsample_latlong(map, height)
        return cls(map.clamp_min(MIN_RADIANCE).log(), learnable)

    @classmethod
    def constant(cls, value, height: int = 32, learnable: bool = True, dtype=torch.float32, device=None):
        """A uniform map: `value` is a scalar or an RGB triple."""
        rgb = torch.as_tensor(value, dtype=dtype, device=device).expand(3)
        return cls.from_tensor(rgb.expand(height, 2 * height, 3).clone(), learnable=learnable)

    @classmethod
    def initial(cls, value: float, height: int, device=None) -> EnvironmentMap:
        return cls.constant(value, height=height, device=device)

    @classmethod
    def from_file(cls, path, height: int | None = None, learnable: bool = False):
        """Read an EXR/HDR (or LDR, decoded to linear) lat-long map, e.g. for relighting; a lossy codec's ringing
        below zero is clamped as `lights.load_envmap` clamps it."""
        rgb, _ = read_image(path)
        rgb = physical_radiance(Path(path), rgb)
        try:
            return cls.from_tensor(rgb, height, learnable, what="environment map")
        except DataError as exc:
            raise file_error(path, str(exc)) from None

    @property
    def map(self) -> Tensor:  # [H, 2H, 3] current linear radiance
        return self.log_map.exp()

    @property
    def height(self) -> int:
        return self.log_map.shape[0]

    def radiance(self, directions: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
        """The light arriving from each direction (bilinear), e.g. to draw the background."""
        return sample_latlong(self.map, directions)

    def prior(self) -> Tensor:  # []
        """Total variation of the map's log radiance: small for a light made of smooth regions and sharp sources, large
        for per-pixel noise (which the photos do not constrain)."""
        return total_variation(self.log_map)

    def step_function(self, levels):
        return prefilter_log_map, tuple(levels), (self.log_map,)

    def fixed(self) -> EnvironmentMap:
        return EnvironmentMap(self.log_map.detach(), learnable=False)

    def prefilter(self, levels=DEFAULT_LEVELS) -> PrefilteredEnvironment:
        """The split-sum maps of the current radiance. A fixed light (not learnable, e.g. a light probe) is
        prefiltered once and the result reused until its map changes (in place or by device or dtype): refinement
        asks for it every step."""
        if self.log_map.requires_grad:
            return prefilter_latlong(self.map, levels)
        key = (tuple(levels), self.log_map._version, self.log_map.data_ptr(), self.log_map.device, self.log_map.dtype)
        cached = getattr(self, "_prefiltered", None)
        if cached is None or cached[0] != key:
            with torch.no_grad():
                cached = (key, prefilter_latlong(self.map, levels))
            self._prefiltered = cached
        return cached[1]

    def lookup_specular(self, directions: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
        """Convenience: prefilter and look up. Prefilter once and reuse the result when shading often."""
        return self.prefilter().lookup_specular(directions, roughness)

    def lookup_diffuse(self, normals: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        return sample_latlong(irradiance_map(self.map), normals)

    def save(self, path) -> None:
        """Write the current map as linear EXR/HDR (atomically)."""
        write_image(path, self.map.detach())

    @classmethod
    def load(cls, path) -> EnvironmentMap:
        return cls.from_file(path)

    @classmethod
    def saved_at(cls, path) -> bool:
        return Path(path).is_file()
