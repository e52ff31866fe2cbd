"""Per-Gaussian directional visibility ("deep shadow maps") and the shadowing it puts on split-sum shading.

Split-sum image-based lighting assumes every direction of the environment reaches every point. On an
object whose parts shadow each other that is wrong, and refinement then bakes the shadows into the base
color. R3DGS, whose geometry the paper builds on, bakes a visibility term per Gaussian by ray tracing;
here it is baked with the rasterizer:

  bake   For each of D directions w_j (the centres of a rows x 2 rows lat-long grid), render the Gaussians
         from a distant camera looking along -w_j. Along each shadow-map pixel the transmittance is a step
         function of depth, T(z) = 1 - sum_{hits k with z_k < z} w_k (the blending weights). A Gaussian's
         visibility towards w_j is T at its own depth minus a bias (twice its own extent along w_j plus a
         small fraction of the object's size, so that a surface does not shadow itself), bilinear between
         the four shadow-map pixels around its projected centre: V [N, D].
  shade  Per Gaussian and view, with n its normal turned to the side more directions reach (`open_side`),
         L_j the light averaged over cell j and dw_j the cell's solid angle, the diffuse and specular light
         are scaled by
             s_diffuse  = sum_j L_j V_j (n.w_j)+ dw_j / sum_j L_j (n.w_j)+ dw_j
             s_specular = sum_j L_j V_j K_j / sum_j L_j K_j,   K_j = exp(kappa (d.w_j - 1)) (n.w_j)+ dw_j
         (d the specular lobe's dominant direction, kappa its von Mises-Fisher sharpness from the
         roughness), per RGB channel. Both are 1 where nothing occludes; the split-sum terms keep their
         full angular resolution and only the ratio comes from the coarse grid.
Interreflections are not modelled.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.material import ROUGHNESS_INDEX
from matspray.render.raster.rasterize import view_weights
from matspray.render.shade.brdf import roughness_to_alpha
from matspray.render.shade.deferred import specular_direction
from matspray.render.shade.envmap import downsample_latlong
from matspray.render.shade.latlong import pixel_directions, pixel_solid_angles
from matspray.settings import setting

TIE = 1e-3  # `open_side`: a normal is turned only where the other side is visible by more than this share
MAX_KAPPA = 1.5  # the specular kernel stays broad: on the coarse grid (rows = 8: 22.5 degree cells) sharper
# kernels shadowed the true G-buffer of the demo object worse (docs/defaults.md)


@dataclass(frozen=True)
class VisibilityConfig:
    rows: int = setting(8, "directions: the centres of a rows x 2 rows lat-long grid")
    resolution: int = setting(128, "shadow-map pixels per side")
    distance: float = setting(30.0, "shadow cameras sit this many bounding radii away (nearly parallel rays)")
    # (demo object, true G-buffer shadowed: 0.08 beat 0.008, 0.023, 0.047 and 0.125)
    bias: float = setting(
        0.08,
        "depth bias as a fraction of the bounding radius, added to twice each Gaussian's extent along the direction",
    )


def visibility_directions(rows: int, device=None) -> tuple[Tensor, Tensor]:  # -> [D, 3] unit, [D] steradians
    """The grid's cell centres and solid angles, in the lat-long order of `downsample_latlong(map, rows)`."""
    directions = pixel_directions(rows, 2 * rows, device=device).reshape(-1, 3)
    return directions, pixel_solid_angles(rows, 2 * rows, device=device).reshape(-1)


@functools.cache
def grid_rows(rows: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:  # -> [3, D], [3, D]
    """`visibility_directions(rows)` as the contiguous [3, D] transposes that `shadow_factors` multiplies by: the
    directions, and the directions times their solid angles (made once per grid, device and dtype: every refinement
    step reads them)."""
    with torch.inference_mode(False):  # kept: tensors that autograd may save, whatever mode the first call ran in
        directions, solid_angles = visibility_directions(rows, device=device)
        directions_t = directions.to(dtype).t().contiguous()
        return directions_t, directions_t * solid_angles.to(dtype)


def shadow_camera(direction: Tensor, center: Tensor, radius: float, config: VisibilityConfig) -> Camera:
    """A distant camera on the `direction` side of the bounding sphere, framing all of it."""
    distance = config.distance * radius
    eye = center.double() + distance * direction.double()
    half_angle = math.atan(1.02 * radius / (distance - radius))
    return Camera.look_at(eye, center.double(), (0.0, 0.0, 1.0), 2 * half_angle, config.resolution, config.resolution)


def transmittance_at(keys: Tensor, cumulative: Tensor, pixel: Tensor, depth01: Tensor) -> Tensor:
    """T(depth) along shadow-map pixels from hits sorted by (pixel, depth).

    keys [M] = pixel + depth01 / 2 of every hit (sorted); cumulative [M + 1] the running sum of their
    weights from 0; pixel [Q] long, depth01 [Q] in [0, 1]. Returns [Q]: 1 - the weights in front.
    """
    start = torch.searchsorted(keys, pixel.double())
    stop = torch.searchsorted(keys, pixel.double() + depth01.double().clamp(0.0, 1.0) / 2)
    return (1.0 - (cumulative[stop] - cumulative[start])).clamp(0.0, 1.0)


@torch.no_grad()
def visibility_from(gaussians: Gaussians, camera: Camera, bias: Tensor) -> Tensor:  # bias [N] -> [N]
    """Each Gaussian's transmittance towards `camera` (1 when nothing in front of it blocks the view)."""
    ids, pixels, weights = view_weights(gaussians, camera)  # sorted by pixel, then front to back
    xy, depth = camera.project(gaussians.means)  # [N, 2] continuous pixel coordinates (centres at +0.5), [N]
    depth = depth.double()
    near, far = float(depth.min()), float(depth.max())
    depth01 = (depth - near) / max(far - near, 1e-12)
    keys = pixels.double() + depth01[ids] / 2
    cumulative = F.pad(torch.cumsum(weights.double(), 0), (1, 0))
    query_depth = (depth - bias.double() - near) / max(far - near, 1e-12)
    corner = torch.floor(xy - 0.5)
    frac = (xy - 0.5 - corner).double()
    visibility = torch.zeros(len(gaussians), dtype=torch.float64, device=xy.device)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        col, row = corner[:, 0].long() + dx, corner[:, 1].long() + dy
        inside = (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        pixel = row.clamp(0, camera.height - 1) * camera.width + col.clamp(0, camera.width - 1)
        t = torch.where(inside, transmittance_at(keys, cumulative, pixel, query_depth), torch.ones_like(visibility))
        wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
        wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
        visibility += wx * wy * t
    return visibility.float()


@torch.no_grad()
def bake_visibility(
    gaussians: Gaussians, config: VisibilityConfig = VisibilityConfig(), progress: bool = False
) -> Tensor:
    """V [N, D]: each Gaussian's visibility towards the D directions of `visibility_directions(config.rows)`."""
    gaussians = gaussians.detach()
    means = gaussians.means
    center = (means.amax(0) + means.amin(0)) / 2
    radius = float((means - center).norm(dim=-1).max()) + 3.0 * float(gaussians.scales.max())
    directions, _ = visibility_directions(config.rows, device=means.device)
    axes = gaussians.scaled_axes()  # [N, 3, 3] columns: the scaled principal axes
    columns = []
    for direction in tqdm(directions, desc="visibility", disable=not progress):
        extent = (axes * direction[:, None]).sum(-2).norm(dim=-1)  # [N] standard deviation along the direction
        bias = 2.0 * extent + config.bias * radius
        columns.append(visibility_from(gaussians, shadow_camera(direction, center, radius, config), bias))
    return torch.stack(columns, dim=-1)


def open_side(visibility: Tensor, facing: Tensor, solid_angles: Tensor) -> Tensor:  # [N, D], [N, D], [D] -> [N, 1]
    """+1 or -1 per Gaussian: the sign that turns its normal to the side of its plane from which more of the
    directions are visible (the outside of the surface); `facing` holds the normals' cosines to the directions.

    Shading turns a normal towards the viewer, since a Gaussian's normal has no sign. Near a silhouette that
    guess is wrong for about half the Gaussians, and their hemisphere then lies inside the object, where
    nothing is visible: measured on a sphere, which nothing shades, the pixels within 2 px of its outline got
    a diffuse factor of 0.80 under a uniform light (docs/dev/relighting-gap.md)."""
    weighted = facing * solid_angles  # [N, D]
    balance = (visibility.to(facing.dtype) * weighted).sum(-1, keepdim=True)  # [N, 1] > 0: more visible in front
    return side_of(balance, weighted.abs().sum(-1, keepdim=True))


def side_of(balance: Tensor, spread: Tensor) -> Tensor:  # [N, 1], [N, 1] -> [N, 1]
    """`open_side` from the visible directions' cosine-weighted sum `balance` and the sum of all |cosines| `spread`
    (both weighted by the solid angles): where both sides are about as visible the viewer's turn stays, so that
    rounding cannot flip it."""
    behind = balance < -TIE * spread
    return 1.0 - 2.0 * behind.to(balance.dtype)


def shadow_factors(
    visibility: Tensor,  # [N, D] in [0, 1]
    normals: Tensor,  # [N, 3] unit, either sign (turned to the open side here)
    view_dirs: Tensor,  # [N, 3] unit, from the Gaussian towards the camera
    roughness: Tensor,  # [N] perceptual
    light_cells: Tensor,  # [rows, 2 rows, 3] the light averaged over the grid's cells (`downsample_latlong`)
) -> Tensor:  # [N, 6]: diffuse RGB and specular RGB scale factors in [0, 1]
    """How much of the split-sum diffuse and specular light actually reaches each Gaussian, over the hemisphere
    on the open side of its plane (`open_side`). The [N, D] part (the kernels and their sums against the light) is
    one autograd Function (`KernelSums`): this runs at every refinement step."""
    rows = light_cells.shape[0]
    if visibility.shape[1] != 2 * rows * rows:
        raise ValueError(f"visibility has {visibility.shape[1]} directions but the light grid has {2 * rows * rows}")
    dtype = normals.dtype
    directions_t, weighted_t = grid_rows(rows, normals.device, dtype)  # [3, D] each
    light_t = light_cells.reshape(-1, 3).to(dtype).t().contiguous()  # [3, D]
    visibility = visibility.to(dtype)
    with torch.no_grad():  # a sign: `open_side` of the normals' cosines, its balance as one product over the directions
        facing = normals @ weighted_t  # [N, D] cosines times solid angles
        balance = (normals * (visibility @ weighted_t.t())).sum(-1, keepdim=True)  # [N, 1]
        side = side_of(balance, facing.abs().sum(-1, keepdim=True))  # [N, 1]
    normals = normals * side  # a product by +-1: exact, so the cosines of the turned normals are `facing`'s, turned
    lobe_dir = F.normalize(specular_direction(normals, view_dirs, roughness), dim=-1, eps=1e-12)
    alpha = roughness_to_alpha(roughness)
    # reflected GGX lobe ~ vMF(1 / (2 alpha^2))
    kappa = (0.5 / alpha.square().clamp_min(1e-6)).clamp(max=MAX_KAPPA)[:, None]  # [N, 1]
    sums = KernelSums.apply(
        normals, kappa * lobe_dir, kappa, facing, side, visibility, weighted_t, directions_t, light_t
    )
    factors = []
    for lit, shadowed in ((sums[0], sums[1]), (sums[2], sums[3])):  # [N, 3] each
        factors.append(torch.where(lit > 1e-12, shadowed / lit.clamp_min(1e-12), torch.ones_like(lit)))
    return torch.cat(factors, dim=-1).clamp(0.0, 1.0)


class KernelSums(torch.autograd.Function):
    """The light's sums over the directions of the diffuse and specular kernels, without and with the visibility:
    for C_j = (n.w_j)+ dw_j and S_j = exp(kappa (d.w_j - 1)) C_j (`shadow_factors`),
        sums [4, N, 3] = sum_j (C_j L_j, C_j V_j L_j, S_j L_j, S_j V_j L_j).

    Autograd of the same expression walks [N, D] tensors about three times as often, and its [N, D] by [D, 3]
    products take the CPU's slow layout; here the four kernels are one [4 N, D] buffer, each product over the
    directions is one matrix product with the [D, 3] factor column-major (the transpose of a contiguous [3, D]),
    and the backward pass works in place. Not twice differentiable."""

    @staticmethod
    def forward(
        ctx,
        turned: Tensor,  # [N, 3] the normals turned to their open side (only their gradient is read)
        lobe_axis: Tensor,  # [N, 3] kappa d, d the specular lobe's unit direction
        kappa: Tensor,  # [N, 1]
        facing: Tensor,  # [N, D] the unturned normals' cosines times solid angles (no gradient; overwritten)
        side: Tensor,  # [N, 1] +-1 (`open_side`): turned = normals * side
        visibility: Tensor,  # [N, D]
        weighted_t: Tensor,  # [3, D] directions times solid angles
        directions_t: Tensor,  # [3, D]
        light_t: Tensor,  # [3, D]
    ) -> Tensor:  # [4, N, 3]
        n, d = facing.shape
        kernels = facing.new_empty(4, n, d)
        cosine, cosine_seen, lobe, lobe_seen = kernels.unbind(0)
        torch.mul(facing, side, out=cosine).clamp_min_(0.0)
        torch.mul(cosine, visibility, out=cosine_seen)
        spread = torch.addmm(-kappa, lobe_axis, directions_t).exp_()  # [N, D] exp(kappa (d.w_j - 1))
        torch.mul(spread, cosine, out=lobe)
        torch.mul(lobe, visibility, out=lobe_seen)
        ctx.save_for_backward(kernels, spread, visibility, weighted_t, directions_t, light_t)
        return (kernels.view(4 * n, d) @ light_t.t()).view(4, n, 3)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):  # [4, N, 3]
        kernels, spread, visibility, weighted_t, directions_t, light_t = ctx.saved_tensors
        _, n, d = kernels.shape
        grad = grad.contiguous().view(4 * n, 3)
        needs = ctx.needs_input_grad
        grad_turned = grad_axis = grad_kappa = grad_light = None
        if needs[8]:
            grad_light = grad.t() @ kernels.view(4 * n, d)  # [3, D]
        if needs[0] or needs[1] or needs[2]:
            cosine, _, lobe, _ = kernels.unbind(0)
            parts = (grad @ light_t).view(4, n, d)  # each sum's gradient spread over the directions
            grad_cosine = parts[0].addcmul_(visibility, parts[1])  # [N, D] through C alone
            grad_lobe = parts[2].addcmul_(visibility, parts[3])  # [N, D] through S
            if needs[0]:
                # S = spread C; C is 0 behind the plane (its sign: a float mask, cheaper than a comparison's)
                grad_cosine.addcmul_(grad_lobe, spread).mul_(cosine.sign())
                grad_turned = grad_cosine @ weighted_t.t()  # [N, 3]
            grad_exponent = grad_lobe.mul_(lobe)  # dS / d(kappa (d.w - 1)) = S
            grad_axis = grad_exponent @ directions_t.t()  # [N, 3]
            grad_kappa = -grad_exponent.sum(-1, keepdim=True)
        return grad_turned, grad_axis, grad_kappa, None, None, None, None, None, grad_light


def light_cells(light, rows: int) -> Tensor:  # Light | PrefilteredLight -> [rows, 2 rows, 3]
    """The light averaged over the visibility grid's cells."""
    source = light.source  # a light's lat-long map
    if source is None:
        raise ValueError(
            "this prefiltered environment does not keep its source map; prefilter with `prefilter_latlong`"
        )
    return downsample_latlong(source, rows)


def visibility_rows(visibility: Tensor) -> int:  # [N, D] with D = 2 rows^2
    rows = math.isqrt(visibility.shape[1] // 2)
    if 2 * rows * rows != visibility.shape[1]:
        raise ValueError(f"visibility must have 2 rows^2 directions, got {visibility.shape[1]}")
    return rows


def gaussian_shadows(
    visibility: Tensor, normals: Tensor, means: Tensor, materials: Tensor, camera: Camera, light
) -> Tensor:
    """`shadow_factors` [N, 6] of Gaussians seen from `camera` under `light`; normals [N, 3] facing the
    camera, materials [N, 5] (`matspray.material` layout: the specular kernel reads the roughness)."""
    roughness = materials[:, ROUGHNESS_INDEX]
    view_dirs = F.normalize(camera.center.to(means) - means, dim=-1)
    normals = F.normalize(normals, dim=-1, eps=1e-12)
    cells = light_cells(light, visibility_rows(visibility))
    return shadow_factors(visibility, normals, view_dirs, roughness, cells)
