"""Alpha blending of sorted (Gaussian, pixel) hits with a hand-written backward pass.

Forward, for the hits of one pixel in front-to-back order:
    G_k     = exp(-(a dx^2 / 2 + b dx dy + c dy^2 / 2)),  (dx, dy) = pixel centre - projected mean
    alpha_k = min(max_alpha, o_k G_k), dropped when o_k G_k < min_alpha
    T_k     = prod_{j<k} (1 - alpha_j)            (float64 log-sum; blending stops before T < min_T)
    out     = sum_k alpha_k T_k f_k
Backward, with q_k = <dL/dout, f_k> and S_k = sum_{j>k} alpha_j T_j q_j on the same pixel:
    dL/dalpha_k = T_k q_k - S_k / (1 - alpha_k),   dL/df_k = alpha_k T_k dL/dout
and the chain rule through G. It matches autograd through the same formulas (see the tests) but
keeps far fewer per-hit tensors alive, which is what the CPU pays for.

With `absgrad_of` (the projected means [N, 2] that `splats` rows 0-1 were taken from), the backward also adds
sum over hits of |dL/dmean x|, |dL/dmean y| (one hit per pixel: each pixel's own gradient, as gsplat's absgrad)
into `absgrad_of.absgrad` [N, 2], created at the first backward and added to by every row band and every later
backward, as `.grad` is (gsplat replaces it at each backward; one backward per render reads the same).
"""

from __future__ import annotations

import torch
from torch import Tensor

from matspray.render.compositing import log_transmittance, surviving_hits
from matspray.render.settings import RasterSettings


def blend_hits(
    splats: Tensor,  # [6, N] rows: projected mean x, y; conic a, b, c; opacity
    values: Tensor,  # [C, N] per-Gaussian values to blend
    gaussian_ids: Tensor,  # [M] long, candidate hits sorted by pixel then front to back
    pixel_ids: Tensor,  # [M] long, pixel index within the band (row-major)
    width: int,
    row_start: int,
    num_pixels: int,
    settings: RasterSettings,
    absgrad_of: Tensor | None = None,  # [N, 2]: receives .absgrad in backward (see the module docstring)
) -> tuple[Tensor, int]:  # [num_pixels, C] blended values, number of blended hits
    out, blended = _BlendHits.apply(
        splats, values, gaussian_ids, pixel_ids, (width, row_start, num_pixels, settings, absgrad_of)
    )
    return out, int(blended)


def _gaussian_response(splats: Tensor, gaussian_ids: Tensor, pixel_ids: Tensor, width: int, row_start: int):
    mean_x, mean_y, a, b, c, opacity = (row.index_select(0, gaussian_ids) for row in splats)
    rows = torch.div(pixel_ids, width, rounding_mode="floor")
    dx = (pixel_ids - rows * width).to(splats.dtype) + 0.5 - mean_x
    dy = rows.to(splats.dtype) + (row_start + 0.5) - mean_y
    response = torch.exp(-(dx * (0.5 * a * dx + b * dy) + 0.5 * c * dy * dy))
    return response, opacity, a, b, c, dx, dy


def _blended_hits(raw: Tensor, pixel_ids: Tensor, num_pixels: int, settings: RasterSettings):
    """The 3DGS alpha test and early termination on candidate hits with raw alpha o G [M]: indices of
    the hits that are blended [K], their alphas [K] and the transmittance in front of them [K]."""
    alphas = torch.where(raw >= settings.min_alpha, raw.clamp(max=settings.max_alpha), torch.zeros_like(raw))
    log_keep, log_T = log_transmittance(alphas, pixel_ids, num_pixels)
    keep = torch.nonzero((alphas > 0) & surviving_hits(log_keep, log_T, settings.min_transmittance)).squeeze(1)
    return keep, alphas.index_select(0, keep), torch.exp(log_T.index_select(0, keep)).to(alphas.dtype)


@torch.no_grad()
def hit_weights(
    splats: Tensor,  # [6, N] as for `blend_hits`
    gaussian_ids: Tensor,  # [M] candidate hits sorted by pixel then front to back
    pixel_ids: Tensor,  # [M] pixel index within the band
    width: int,
    row_start: int,
    num_pixels: int,
    settings: RasterSettings,
) -> tuple[Tensor, Tensor, Tensor]:  # Gaussian ids [K], pixel ids [K], weights alpha_k T_k [K]
    """The blending weights `blend_hits` uses, without gradients: with them a frozen view's image of
    any features is one sparse product, out[p] = sum_k weight_k f[gaussian_k]."""
    response, opacity, *_ = _gaussian_response(splats, gaussian_ids, pixel_ids, width, row_start)
    keep, alphas, transmittance = _blended_hits(opacity * response, pixel_ids, num_pixels, settings)
    return gaussian_ids.index_select(0, keep), pixel_ids.index_select(0, keep), alphas * transmittance


class _BlendHits(torch.autograd.Function):
    @staticmethod
    def forward(ctx, splats, values, gaussian_ids, pixel_ids, band):
        width, row_start, num_pixels, settings, absgrad_of = band
        response, opacity, a, b, c, dx, dy = _gaussian_response(splats, gaussian_ids, pixel_ids, width, row_start)
        raw = opacity * response
        keep, alphas, transmittance = _blended_hits(raw, pixel_ids, num_pixels, settings)
        gaussian_ids, pixel_ids = gaussian_ids.index_select(0, keep), pixel_ids.index_select(0, keep)
        raw = raw.index_select(0, keep)
        weights = alphas * transmittance
        hit_values = torch.stack([row.index_select(0, gaussian_ids) for row in values])  # [C, M]
        out = values.new_zeros(num_pixels, values.shape[0])
        out.index_add_(0, pixel_ids, (hit_values * weights).t())
        ctx.save_for_backward(
            gaussian_ids,
            pixel_ids,
            alphas,
            transmittance,
            raw <= settings.max_alpha,
            response.index_select(0, keep),
            a.index_select(0, keep),
            b.index_select(0, keep),
            c.index_select(0, keep),
            dx.index_select(0, keep),
            dy.index_select(0, keep),
            hit_values,
        )
        ctx.sizes = (splats.shape[1], num_pixels)
        ctx.absgrad_of = absgrad_of
        count = torch.tensor(int(keep.numel()), device="cpu")  # a host-side count, wherever the hits are
        ctx.mark_non_differentiable(count)
        return out, count

    @staticmethod
    def backward(ctx, grad_out, _grad_count):
        gaussian_ids, pixel_ids, alphas, transmittance, unclamped, response, a, b, c, dx, dy, hit_values = (
            ctx.saved_tensors
        )
        num_gaussians, num_pixels = ctx.sizes
        weights = alphas * transmittance
        grad_hit = grad_out.index_select(0, pixel_ids).t()  # [C, M]
        grad_values = grad_out.new_zeros(hit_values.shape[0], num_gaussians)
        grad_values.index_add_(1, gaussian_ids, grad_hit * weights)

        q = (grad_hit * hit_values).sum(dim=0)  # [M] dL/dweight
        contribution = (weights * q).double()
        inclusive = torch.cumsum(contribution, 0)
        counts = torch.bincount(pixel_ids, minlength=num_pixels)
        ends = (torch.cumsum(counts, 0) - 1).index_select(0, pixel_ids)
        behind = (inclusive.index_select(0, ends) - inclusive).to(alphas.dtype)  # S_k
        grad_alpha = transmittance * q - behind / (1.0 - alphas)
        grad_raw = torch.where(unclamped, grad_alpha, torch.zeros_like(grad_alpha))
        grad_opacity = grad_raw * response
        grad_exponent = grad_raw * alphas  # alpha = o G when unclamped; d(o G)/d(exponent) = o G
        grads = (
            grad_exponent * (a * dx + b * dy),  # mean x
            grad_exponent * (b * dx + c * dy),  # mean y
            -0.5 * grad_exponent * dx * dx,  # conic a
            -grad_exponent * dx * dy,  # conic b
            -0.5 * grad_exponent * dy * dy,  # conic c
            grad_opacity,
        )
        grad_splats = grad_out.new_zeros(6, num_gaussians)
        for row, grad in enumerate(grads):
            grad_splats[row].index_add_(0, gaussian_ids, grad)
        if ctx.absgrad_of is not None:
            add_absgrad(ctx.absgrad_of, gaussian_ids, torch.stack(grads[:2], dim=-1))
        return grad_splats, grad_values, None, None, None


def add_absgrad(means2d: Tensor, gaussian_ids: Tensor, grad_per_hit: Tensor) -> None:  # [N, 2], [M], [M, 2]
    """means2d.absgrad [N, 2] += sum over each Gaussian's hits of |grad_per_hit| (created as zeros when absent)."""
    if getattr(means2d, "absgrad", None) is None:
        means2d.absgrad = torch.zeros_like(means2d, memory_format=torch.contiguous_format).detach()
    means2d.absgrad.index_add_(0, gaussian_ids, grad_per_hit.abs().to(means2d.dtype))
