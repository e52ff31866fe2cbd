import math

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from matspray.data.images import linear_to_srgb
from matspray.errors import ConfigError, DataError
from matspray.eval import (
    align_scale,
    average_metrics,
    channel_scale,
    composite_on_background,
    evaluate_images,
    metallic_psnr_over_objects,
    object_metallic_psnr,
    psnr,
    ssim,
)


def rand(*shape, seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


# ------------------------------------------------------------------------------------------ PSNR
def test_psnr_of_a_constant_offset_is_minus_20_log10_of_it():
    target = torch.full((16, 12, 3), 0.3)
    assert psnr(target + 0.1, target) == pytest.approx(20.0, abs=1e-5)  # mse 0.01
    assert psnr(target + 0.01, target) == pytest.approx(40.0, abs=1e-4)


def test_psnr_of_identical_images_is_infinite():
    image = rand(8, 8, 3)
    assert psnr(image, image) == math.inf


def test_psnr_with_mask_counts_only_the_masked_pixels():
    target = torch.zeros(10, 10, 3, dtype=torch.float64)
    pred = target.clone()
    pred[:, 5:] = 0.2  # error only on the right half
    mask = torch.zeros(10, 10)
    mask[:, :5] = 1
    assert psnr(pred, target, mask) == math.inf
    assert psnr(pred, target, 1 - mask) == pytest.approx(-10 * math.log10(0.04))
    assert psnr(pred, target) == pytest.approx(-10 * math.log10(0.02))  # half the pixels are wrong
    weights = torch.full((10, 10), 0.25)
    assert psnr(pred, target, weights) == pytest.approx(-10 * math.log10(0.02))  # a uniform weight changes nothing


@pytest.mark.parametrize(
    "pred,target,mask,message",
    [
        (torch.full((4, 4, 3), 1.5), torch.zeros(4, 4, 3), None, r"pred: values must be in \[0, 1\]"),
        (torch.zeros(4, 4, 3), torch.zeros(4, 5, 3), None, "differ in shape"),
        (torch.full((4, 4, 3), float("nan")), torch.zeros(4, 4, 3), None, "NaN"),
        (torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.zeros(4, 4), "selects no pixels"),
        (torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.ones(3, 4), "does not match"),
        (torch.zeros(2, 4, 4, 3), torch.zeros(2, 4, 4, 3), None, r"expected an image \[H, W\]"),
    ],
)
def test_psnr_rejects_bad_input(pred, target, mask, message):
    with pytest.raises(DataError, match=message):
        psnr(pred, target, mask)


# ------------------------------------------------------------------------------------------ SSIM
def ssim_reference(x: np.ndarray, y: np.ndarray) -> float:
    """scikit-image's recipe written out in numpy: a full 11x11 Gaussian window (truncate 3.5 at
    sigma 1.5) slid over the image with symmetric padding, the 5-pixel border cropped."""
    c1, c2, pad = 0.01**2, 0.03**2, 5
    g = np.exp(-((np.arange(-pad, pad + 1)) ** 2) / (2 * 1.5**2))
    window = np.outer(g, g) / np.outer(g, g).sum()  # [11, 11]

    def filtered(a):  # [H, W] -> [H, W], reflect-padded ('symmetric' in numpy = scipy's 'reflect')
        windows = sliding_window_view(np.pad(a, pad, mode="symmetric"), (11, 11))  # [H, W, 11, 11]
        return np.einsum("hwij,ij->hw", windows, window)

    values = []
    for c in range(x.shape[-1]):
        a, b = x[..., c], y[..., c]
        ua, ub = filtered(a), filtered(b)
        va, vb, cov = filtered(a * a) - ua * ua, filtered(b * b) - ub * ub, filtered(a * b) - ua * ub
        s = ((2 * ua * ub + c1) * (2 * cov + c2)) / ((ua**2 + ub**2 + c1) * (va + vb + c2))
        values.append(s[pad:-pad, pad:-pad].mean())
    return float(np.mean(values))


def test_ssim_of_identical_images_is_one():
    image = rand(20, 17, 3)
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-12)


def test_ssim_of_constant_images_is_the_luminance_term():
    a, b = 0.2, 0.7
    expected = (2 * a * b + 0.01**2) / (a * a + b * b + 0.01**2)  # variances and covariance are zero
    pair = torch.full((15, 15, 1), a, dtype=torch.float64), torch.full((15, 15, 1), b, dtype=torch.float64)
    assert ssim(*pair) == pytest.approx(expected, rel=1e-9)


def test_ssim_of_an_11x11_image_is_one_window_computed_by_hand():
    x, y = rand(11, 11, seed=1).numpy(), rand(11, 11, seed=2).numpy()
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    mx, my = (w * x).sum(), (w * y).sum()
    vx, vy, cxy = (w * x * x).sum() - mx**2, (w * y * y).sum() - my**2, (w * x * y).sum() - mx * my
    expected = (2 * mx * my + 1e-4) * (2 * cxy + 9e-4) / ((mx**2 + my**2 + 1e-4) * (vx + vy + 9e-4))
    assert ssim(x, y) == pytest.approx(expected, rel=1e-10)


def test_ssim_matches_an_independent_numpy_computation():
    x = rand(40, 37, 3, seed=3)
    y = (0.7 * x + 0.3 * rand(40, 37, 3, seed=4)).clamp(0, 1)
    expected = ssim_reference(x.numpy(), y.numpy())
    assert ssim(x, y) == pytest.approx(expected, abs=1e-10)
    assert ssim(y, x) == pytest.approx(expected, abs=1e-10)
    assert 0.3 < expected < 0.95  # a meaningful, non-trivial pair


def test_the_ssim_training_loss_has_the_gradient_of_its_values():
    from matspray.metrics import ssim_loss

    x, y = rand(14, 13, 2, seed=5), rand(14, 13, 2, seed=6)
    assert float(ssim_loss(x, y)) == pytest.approx(1.0 - ssim_reference(x.numpy(), y.numpy()), abs=1e-10)
    assert torch.autograd.gradcheck(lambda image: ssim_loss(image, y), (x.requires_grad_(),))


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(DataError, match="at least 11x11"):
        ssim(torch.zeros(10, 30, 3), torch.zeros(10, 30, 3))


# ------------------------------------------------------------------------------------------ compositing
def test_composite_keeps_the_object_and_replaces_the_background():
    image = torch.tensor([[[0.2, 0.4, 0.8], [0.2, 0.4, 0.8], [0.2, 0.4, 0.8]]])  # [1, 3, 3]
    mask = torch.tensor([[1.0, 0.0, 0.5]])
    out = composite_on_background(image, mask, background=1.0)
    assert torch.allclose(out[0, 0], linear_to_srgb(image[0, 0]))
    assert torch.allclose(out[0, 1], torch.ones(3))
    assert torch.allclose(out[0, 2], linear_to_srgb(0.5 * image[0, 2] + 0.5))
    raw = composite_on_background(image * 3, mask, background=(0.0, 0.5, 0.0), encoding="raw")
    assert torch.allclose(raw[0, 0], torch.tensor([0.6, 1.0, 1.0]))  # clamped to [0, 1]
    assert torch.allclose(raw[0, 1], torch.tensor([0.0, 0.5, 0.0]))


def test_composite_rejects_bad_arguments():
    image, mask = torch.zeros(4, 4, 3), torch.ones(4, 4)
    with pytest.raises(ConfigError, match="encoding must be one of"):
        composite_on_background(image, mask, encoding="gamma")
    with pytest.raises(ConfigError, match="background"):
        composite_on_background(image, mask, background=(1.0, 0.0))
    with pytest.raises(DataError, match="mask: shape"):
        composite_on_background(image, torch.ones(4, 5))
    with pytest.raises(DataError, match=r"mask: values must be finite and in \[0, 1\]"):
        composite_on_background(image, mask * 2)


# ------------------------------------------------------------------------------------------ scale alignment
def test_align_scale_undoes_a_per_channel_scale_on_the_object():
    target = 0.05 + 0.9 * rand(2, 6, 7, 3, seed=5)  # two views
    mask = rand(2, 6, 7, seed=6) > 0.3
    pred = target / torch.tensor([2.0, 0.5, 1.25], dtype=torch.float64)
    pred[~mask] = 0.9  # the background does not influence the ratio
    assert torch.allclose(channel_scale(pred, target, mask), torch.tensor([2.0, 0.5, 1.25], dtype=torch.float64))
    assert torch.allclose(align_scale(pred, target, mask)[mask], target[mask])


def test_align_scale_uses_the_median_so_outliers_do_not_move_it():
    target = torch.full((1, 5, 3), 0.5, dtype=torch.float64)
    pred = torch.full((1, 5, 3), 0.25, dtype=torch.float64)
    pred[0, 0] = 1e-9  # a black pixel: ratio 5e8 (floored), one of five
    scale = channel_scale(pred, target, torch.ones(1, 5, dtype=torch.bool))
    assert torch.allclose(scale, torch.full((3,), 2.0, dtype=torch.float64))


def test_align_scale_needs_object_pixels():
    with pytest.raises(DataError, match="selects no object pixels"):
        align_scale(torch.ones(3, 3, 3), torch.ones(3, 3, 3), torch.zeros(3, 3))


# ------------------------------------------------------------------------------------------ metallic rule
def test_non_metallic_object_predicted_all_zero_is_infinite_and_left_out():
    mask = torch.zeros(2, 8, 8)
    mask[:, 2:6, 2:6] = 1
    zeros = torch.zeros(2, 8, 8)
    outside = torch.zeros(2, 8, 8)
    outside[:, 0, 0] = 0.7  # prediction off the object (mask 0) does not count
    metallic_gt = mask * 1.0
    metallic_pred = mask * 0.9  # error 0.1 on 16 of 64 pixels per view: mse 0.0025
    result = metallic_psnr_over_objects(
        [
            (zeros, zeros, mask),  # non-metallic, predicted all zero: infinite
            (outside, zeros, mask),  # same, with junk on the background: infinite
            (metallic_pred, metallic_gt, mask),  # 26.0206 dB
            (zeros + 0.1 * mask, zeros, mask),  # non-metallic, predicted 0.1: mse 0.0025 too
        ]
    )
    assert result.infinite == 2
    assert result.per_object[:2] == [math.inf, math.inf]
    expected = -10 * math.log10(0.0025)
    assert result.per_object[2] == pytest.approx(expected)
    assert result.mean == pytest.approx(expected)  # the mean of the two finite objects


def test_metallic_psnr_pools_views_so_one_exact_view_does_not_make_it_infinite():
    mask = torch.ones(2, 4, 4)
    gt = torch.stack([torch.zeros(4, 4), torch.ones(4, 4)])  # the metal is seen in view 1 only
    pred = torch.stack([torch.zeros(4, 4), torch.full((4, 4), 0.8)])
    assert object_metallic_psnr(pred, gt, mask) == pytest.approx(-10 * math.log10(0.04 / 2))


def test_metallic_psnr_when_every_object_is_infinite_has_no_mean():
    mask = torch.ones(8, 8)
    result = metallic_psnr_over_objects([(torch.zeros(8, 8), torch.zeros(8, 8), mask)] * 3)
    assert result == (None, 3, [math.inf] * 3)


def test_metallic_psnr_rejects_bad_input():
    with pytest.raises(DataError, match="no objects"):
        metallic_psnr_over_objects([])
    with pytest.raises(DataError, match="same shape"):
        object_metallic_psnr(torch.zeros(2, 4, 4), torch.zeros(2, 4, 4), torch.ones(4, 4))
    with pytest.raises(DataError, match=r"pred: metallic values must be finite and in \[0, 1\]"):
        object_metallic_psnr(torch.full((4, 4), 2.0), torch.zeros(4, 4), torch.ones(4, 4))


# ------------------------------------------------------------------------------------------ evaluate_images
class RecordingMetric:
    source = "test double"

    def __init__(self):
        self.shapes = []

    def distance(self, pred, target):
        self.shapes.append((tuple(pred.shape), tuple(target.shape)))
        return float((pred - target).abs().mean())


def test_evaluate_images_composites_on_the_object():
    image = rand(16, 16, 3, seed=7)
    mask = torch.zeros(16, 16)
    mask[4:12, 4:12] = 1
    other = image.clone()
    other[mask == 0] = 0.0  # differs only off the object
    assert evaluate_images(other, image, mask) == {"psnr": math.inf, "ssim": pytest.approx(1.0), "lpips": None}
    shifted = (image + 0.1 * mask[..., None]).clamp(0, 1)
    expected = psnr(composite_on_background(shifted, mask), composite_on_background(image, mask))
    assert evaluate_images(shifted, image, mask)["psnr"] == pytest.approx(expected)


def test_evaluate_images_repeats_grey_maps_to_rgb_for_lpips_only():
    metric = RecordingMetric()
    roughness = rand(16, 16, seed=8)
    result = evaluate_images(roughness, roughness * 0.5, torch.ones(16, 16), lpips=metric, encoding="raw")
    assert metric.shapes == [((16, 16, 3), (16, 16, 3))]
    assert result["psnr"] == pytest.approx(psnr(roughness, roughness * 0.5))
    assert result["lpips"] == pytest.approx(float((roughness * 0.5).mean()))


def test_average_metrics_keeps_unavailable_and_infinite_values():
    records = [{"psnr": 20.0, "ssim": 0.5, "lpips": None}, {"psnr": 30.0, "ssim": 0.7, "lpips": None}]
    assert average_metrics(records) == {"psnr": 25.0, "ssim": pytest.approx(0.6), "lpips": None}
    assert average_metrics([{"psnr": math.inf}, {"psnr": 10.0}]) == {"psnr": math.inf}
    assert average_metrics([]) == {}
