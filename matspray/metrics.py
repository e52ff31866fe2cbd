"""PSNR and SSIM between two images with values in [0, 1].

Images are [H, W, C] (a [H, W] map counts as one channel), compared as given: callers composite
prediction and ground truth on the object first (`matspray.eval.masked.composite_on_background`),
so both are sRGB-encoded (colour) or raw (roughness, metallic) values clamped to [0, 1]. Both
metrics take an optional region `mask` [H, W] of weights (the union of the silhouettes, see
`matspray.eval.masked.union_weights`); without it they cover the full image.

SSIM follows Wang et al. 2004: an 11-tap Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03,
data range 1, statistics over the window positions that lie fully inside the image ("valid"
filtering, as the authors' MATLAB code), averaged over positions and channels. That equals
scikit-image's `structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from matspray.errors import DataError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
RANGE_TOLERANCE = 1e-6  # values this far outside [0, 1] still count as inside (float rounding)


# ------------------------------------------------------------------------------------------ input checks
def as_image(values, name: str) -> Tensor:
    """`values` as a float64 tensor [H, W, C]; a [H, W] map becomes [H, W, 1]. Rejects NaN/Inf."""
    image = torch.as_tensor(values)
    if image.dim() == 2:
        image = image[..., None]
    if image.dim() != 3:
        raise DataError(f"{name}: expected an image [H, W] or [H, W, C], got shape {list(image.shape)}")
    image = image.to(torch.float64)
    if not torch.isfinite(image).all():
        raise DataError(f"{name}: contains NaN or Inf values")
    return image


def as_unit_image(values, name: str) -> Tensor:
    """Like `as_image`, and the values must lie in [0, 1]."""
    image = as_image(values, name)
    low, high = float(image.min()), float(image.max())
    if low < -RANGE_TOLERANCE or high > 1.0 + RANGE_TOLERANCE:
        raise DataError(
            f"{name}: values must be in [0, 1] for image metrics, found [{low:.4g}, {high:.4g}] "
            "(composite and clamp first with matspray.eval.composite_on_background)"
        )
    return image


def unit_image_pair(pred, target) -> tuple[Tensor, Tensor]:  # -> [H, W, C], [H, W, C] float64
    pred = as_unit_image(pred, "pred")
    target = as_unit_image(target, "target").to(pred.device)
    if pred.shape != target.shape:
        raise DataError(f"pred {list(pred.shape)} and target {list(target.shape)} differ in shape")
    return pred, target


def as_weights(mask, shape: tuple[int, int], device) -> Tensor:
    """A mask [H, W] (bool or weights in [0, 1]) as float64 weights on `device`."""
    weights = torch.as_tensor(mask).to(device=device, dtype=torch.float64)
    if weights.dim() == 3 and weights.shape[-1] == 1:
        weights = weights[..., 0]
    if tuple(weights.shape) != tuple(shape):
        raise DataError(f"mask: shape {list(weights.shape)} does not match the image's {list(shape)}")
    if not torch.isfinite(weights).all() or float(weights.min()) < 0.0 or float(weights.max()) > 1.0:
        raise DataError("mask: values must be finite and in [0, 1]")
    return weights


# ------------------------------------------------------------------------------------------ PSNR
def psnr_from_mse(mse: float) -> float:
    """Peak signal-to-noise ratio in dB for data range 1; infinite when the error is zero."""
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def mse(pred, target, mask=None) -> float:
    """Mean squared error over pixels and channels; with `mask` [H, W], a mean weighted by it."""
    pred, target = unit_image_pair(pred, target)
    squared = (pred - target) ** 2  # [H, W, C]
    if mask is None:
        return float(squared.mean())
    weights = as_weights(mask, pred.shape[:2], pred.device)  # [H, W]
    total = float(weights.sum())
    if total == 0.0:
        raise DataError("mask: selects no pixels; PSNR over an empty region is undefined")
    return float((squared * weights[..., None]).sum()) / (total * pred.shape[-1])


def psnr(pred, target, mask=None) -> float:
    """PSNR in dB of images [H, W, C] in [0, 1]; `mask` [H, W] restricts (weights) the pixels."""
    return psnr_from_mse(mse(pred, target, mask))


# ------------------------------------------------------------------------------------------ SSIM
def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float64, device=None) -> Tensor:
    """Normalised 1D Gaussian taps [size], centred (MATLAB's fspecial('gaussian') is its outer product)."""
    offsets = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    taps = torch.exp(-(offsets**2) / (2 * sigma**2))
    return taps / taps.sum()


_WINDOWS: dict[tuple, tuple[Tensor, Tensor]] = {}  # (planes, dtype, device) -> the SSIM window's two kernels


def _window_kernels(taps: Tensor, count: int) -> tuple[Tensor, Tensor]:  # [K] -> [B, 1, 1, K], [B, 1, K, 1]
    k = taps.shape[0]
    return taps.view(1, 1, 1, k).expand(count, 1, 1, k), taps.view(1, 1, k, 1).expand(count, 1, k, 1)


def _ssim_kernels(count: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """The SSIM window's `_window_kernels` for `count` planes, made once (the training losses ask every step)."""
    key = (count, dtype, str(device))
    if key not in _WINDOWS:
        taps = gaussian_window(dtype=dtype, device=device)
        _WINDOWS[key] = tuple(kernel.contiguous() for kernel in _window_kernels(taps, count))
    return _WINDOWS[key]


def _window_mean(x: Tensor, taps: Tensor | None = None) -> Tensor:  # [..., H, W], [K] -> [..., H-K+1, W-K+1]
    """The separable window's weighted mean at every valid position (`taps` None: the SSIM window): two depthwise
    convolutions (rows, then columns), one plane per leading index. The convolution's own backward is one pass each
    way, where shifted slices summed in autograd cost a full-size zero tensor and an add per slice
    (docs/dev/rasterizer.md has the timing)."""
    planes = x.reshape(1, -1, *x.shape[-2:])  # [1, B, H, W]
    count = planes.shape[1]
    if taps is None:
        row_kernel, column_kernel = _ssim_kernels(count, x.dtype, x.device)
    else:
        row_kernel, column_kernel = _window_kernels(taps.to(x), count)
    out = F.conv2d(F.conv2d(planes, row_kernel, groups=count), column_kernel, groups=count)
    return out.reshape(*x.shape[:-2], *out.shape[-2:])


def ssim_map(pred, target) -> Tensor:
    """Local SSIM [H-10, W-10, C] at every window position inside the image (validated, float64)."""
    pred, target = unit_image_pair(pred, target)
    height, width, _ = pred.shape
    if min(height, width) < SSIM_WINDOW:
        raise DataError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {height}x{width}")
    return local_ssim(pred, target)


def local_ssim(x: Tensor, y: Tensor) -> Tensor:  # [H, W, C], [H, W, C] -> [H-10, W-10, C]
    """SSIM statistics of two images at every valid window position; differentiable, any float dtype.
    No input checks: the training loss calls it on every step."""
    x, y = x.permute(2, 0, 1), y.permute(2, 0, 1)  # [C, H, W]
    means = _window_mean(torch.cat([x, y, x * x, y * y, x * y]))  # [5C, H-10, W-10] in one pass
    mean_x, mean_y, mean_xx, mean_yy, mean_xy = means.split(x.shape[0])
    mean_x2, mean_y2, mean_x_y = mean_x**2, mean_y**2, mean_x * mean_y
    var_x = mean_xx - mean_x2
    var_y = mean_yy - mean_y2
    cov_xy = mean_xy - mean_x_y
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # data range 1
    numerator = (2 * mean_x_y + c1) * (2 * cov_xy + c2)
    denominator = (mean_x2 + mean_y2 + c1) * (var_x + var_y + c2)
    return (numerator / denominator).permute(1, 2, 0)


def ssim_loss(pred: Tensor, target: Tensor) -> Tensor:  # [H, W, C], [H, W, C] in [0, 1] -> [] (1 - SSIM)
    """D-SSIM term of the 3DGS photometric loss: 1 - mean local SSIM, differentiable."""
    return 1.0 - local_ssim(pred, target).mean()


def ssim(pred, target, mask=None) -> float:
    """Mean SSIM of images [H, W, C] in [0, 1] (Gaussian window 11, sigma 1.5; Wang et al. 2004).

    With `mask` [H, W] (weights in [0, 1]) the mean over window positions is weighted by how much of
    each window lies in the region, measured with the window's own Gaussian taps (the weights'
    windowed mean): windows wholly inside count fully, windows straddling the edge partly, windows
    off it not at all. Every pixel with weight > 0 reaches some valid window (the taps are all
    positive), so only an empty mask is refused; an all-ones mask gives the plain mean.
    """
    local = ssim_map(pred, target)  # [H-10, W-10, C]
    if mask is None:
        return float(local.mean())
    height, width = local.shape[0] + SSIM_WINDOW - 1, local.shape[1] + SSIM_WINDOW - 1
    weights = as_weights(mask, (height, width), local.device)  # [H, W]
    windows = _window_mean(weights, gaussian_window(dtype=weights.dtype, device=weights.device))  # [H-10, W-10]
    total = float(windows.sum())
    if total == 0.0:
        raise DataError("mask: selects no pixels; SSIM over an empty region is undefined")
    return float((local * windows[..., None]).sum()) / (total * local.shape[-1])


# ------------------------------------------------------------------------------------------ sharpness
def gradient_energy(image, mask) -> float:  # [H, W, C] (or [H, W]) in [0, 1], [H, W] weights in [0, 1] -> >= 0
    """How much fine detail an image holds inside a region: the sum, over horizontally and vertically neighbouring
    pixel pairs and over channels, of the squared difference, each pair weighted by the product of its two pixels'
    weights (a pair with a pixel outside the region counts nothing, so the region's edge adds no detail)."""
    image = as_unit_image(image, "image")
    weights = as_weights(mask, tuple(image.shape[:2]), image.device)
    across = (image[:, 1:] - image[:, :-1]).square().sum(-1) * weights[:, 1:] * weights[:, :-1]  # [H, W - 1]
    down = (image[1:] - image[:-1]).square().sum(-1) * weights[1:] * weights[:-1]  # [H - 1, W]
    return float(across.sum() + down.sum())
