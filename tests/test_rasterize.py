"""The torch rasterizer against the per-pixel reference (matspray.render.raster.reference.splat_pixels), and its
gradients."""

from __future__ import annotations

import math

import pytest
import torch

from matspray.data.camera import Camera
from matspray.errors import ConfigError
from matspray.gaussians import Gaussians
from matspray.render.raster.rasterize import rasterize
from matspray.render.raster.reference import splat_pixels
from matspray.render.settings import RasterSettings
from tests.scenes import stacked_opaque_gaussians


def random_scene(n: int, seed: int, dtype=torch.float32, width: int = 16, height: int = 12, max_opacity: float = 0.97):
    """n Gaussians in a 1.2-unit cube around the origin, seen by a camera 4 units away."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    log_scales = torch.log(0.04 + 0.12 * torch.rand(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opacity = 0.05 + (max_opacity - 0.05) * torch.rand(n, generator=g)
    sh = torch.randn(n, 1, 3, generator=g) * 0.5
    gaussians = Gaussians(means, log_scales, quats, torch.logit(opacity), sh).to(dtype=dtype)
    camera = Camera.look_at([0.3, -4.0, 0.8], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(30), width, height)
    features = torch.rand(n, 3, generator=g).to(dtype)
    return gaussians, camera, features


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(seed):
    gaussians, camera, features = random_scene(40, seed)
    background = torch.tensor([0.2, 0.5, 1.0])
    out = rasterize(gaussians, camera, features, background)
    image, alpha, depth = splat_pixels(gaussians, camera, features, background)
    assert out.features.shape == (12, 16, 3) and out.alpha.shape == (12, 16) and out.depth.shape == (12, 16)
    assert alpha.max() > 0.9 and (alpha < 0.5).any()  # the scene has both covered and open pixels
    torch.testing.assert_close(out.features.double(), image, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.alpha.double(), alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.depth.double(), depth, atol=1e-5 * 5, rtol=1e-5)  # depth ~4, float32


def test_early_termination_matches_reference():
    """Eight nearly opaque Gaussians stacked on the optical axis: blending stops once the transmittance
    would fall below 1e-4, so the farthest ones must not appear (they do without termination)."""
    n = 8
    gaussians, camera, features = stacked_opaque_gaussians(n)
    out = rasterize(gaussians, camera, features)
    image, alpha, depth = splat_pixels(gaussians, camera, features, torch.zeros(n))
    torch.testing.assert_close(out.features.double(), image, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.alpha.double(), alpha, atol=1e-5, rtol=0)
    assert out.features[3:5, 3:5, -1].max() == 0  # the four central pixels stop early
    assert (
        rasterize(gaussians, camera, features, settings=RasterSettings(min_transmittance=0.0))
        .features[3:5, 3:5, -1]
        .min()
        > 1e-6
    )


def test_row_bands_give_the_same_image_and_gradients():
    gaussians, camera, features = random_scene(30, 3)
    results = []
    for max_pairs in (1 << 23, 40):
        g = Gaussians(
            *(
                t.clone().requires_grad_(True)
                for t in (
                    gaussians.means,
                    gaussians.log_scales,
                    gaussians.quats,
                    gaussians.opacity_logits,
                    gaussians.sh,
                )
            )
        )
        out = rasterize(g, camera, features, max_pairs=max_pairs)
        (out.features.square().sum() + out.depth.sum()).backward()
        results.append((out.features.detach(), out.alpha.detach(), g.means.grad, g.log_scales.grad))
    for whole, banded in zip(*results):
        torch.testing.assert_close(banded, whole, atol=1e-5, rtol=1e-4)  # float32 summation order


def test_gradcheck_float64():
    gaussians, camera, features = random_scene(4, 5, dtype=torch.float64, width=7, height=6, max_opacity=0.8)
    gaussians.log_scales = gaussians.log_scales + math.log(2.5)  # footprints of a few pixels, overlapping
    background = torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64)

    def render(means, log_scales, quats, opacity_logits, feats):
        g = Gaussians(means, log_scales, quats, opacity_logits, gaussians.sh)
        out = rasterize(g, camera, feats, background)
        return out.features, out.alpha, out.depth

    inputs = tuple(
        t.clone().requires_grad_(True)
        for t in (gaussians.means, gaussians.log_scales, gaussians.quats, gaussians.opacity_logits, features.double())
    )
    assert render(*inputs)[1].max() > 0.5
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_screen_space_gradients_and_radii():
    gaussians, camera, features = random_scene(20, 6)
    behind = gaussians.means.clone()
    behind[0] = camera.center + (camera.center - 0.0)  # far behind the camera
    gaussians.means = behind.requires_grad_(True)
    out = rasterize(gaussians, camera, features)
    assert out.screen_grads is None
    out.retain_screen_grads()
    out.features.sum().backward()
    grads = out.screen_grads
    assert grads is not None and grads.shape == (20, 2)
    assert out.radii[0] == 0 and not out.visible[0]
    assert (grads[~out.visible] == 0).all()
    assert grads[out.visible].abs().sum() > 0


@pytest.mark.parametrize("max_pairs", [1 << 23, 40])
def test_absgrad_is_the_sum_of_per_pixel_gradient_magnitudes(max_pairs):
    """screen_absgrads against brute force: |d loss_p / d means2d| of each pixel's loss on its own, summed (in
    one band and in several: every band adds its hits)."""
    gaussians, camera, features = random_scene(6, 8, dtype=torch.float64, width=7, height=6, max_opacity=1.0)
    gaussians.log_scales = gaussians.log_scales + math.log(2.5)  # footprints of a few pixels, overlapping
    gaussians.opacity_logits[0] = 20.0  # an opaque one: its alpha clamps, and stops what is behind it
    gaussians.means.requires_grad_(True)
    out = rasterize(
        gaussians,
        camera,
        features.double(),
        torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64),
        absgrad=True,
        max_pairs=max_pairs,
    )
    out.retain_screen_grads()
    per_pixel = (
        (out.features * torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64)).sum(-1)
        + out.alpha.square()
        + 0.1 * out.depth
    )
    per_pixel.sum().backward(retain_graph=True)
    absgrads, grads = out.screen_absgrads.clone(), out.screen_grads.clone()
    reference = torch.zeros_like(absgrads)
    for loss in per_pixel.reshape(-1):
        reference += torch.autograd.grad(loss, out.screen, retain_graph=True)[0].abs()
    torch.testing.assert_close(absgrads, reference, atol=1e-12, rtol=1e-10)
    assert (reference > grads.abs() + 1e-6).any()  # pixels pull some centres different ways: not |screen_grads|
    assert out.visible.all() and (reference[out.visible] > 0).all()


def test_expected_depth_is_the_surface_depth():
    n = 1
    gaussians = Gaussians(
        torch.zeros(n, 3),
        torch.full((n, 3), math.log(0.2)),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.logit(torch.tensor([0.9])),
        torch.zeros(n, 1, 3),
    )
    camera = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], math.radians(30), 9, 9)
    out = rasterize(gaussians, camera, torch.ones(n, 1))
    covered = out.alpha > 0
    torch.testing.assert_close(out.expected_depth[covered], torch.full_like(out.alpha[covered], 3.0))
    assert (out.expected_depth[~covered] == 0).all()
    torch.testing.assert_close(out.features[..., 0], out.alpha)  # feature 1 everywhere renders alpha


def test_rejects_bad_arguments():
    gaussians, camera, features = random_scene(5, 0)
    with pytest.raises(ValueError, match="features must be"):
        rasterize(gaussians, camera, features[:4])
    with pytest.raises(ValueError, match="background must be"):
        rasterize(gaussians, camera, features, torch.zeros(2))
    with pytest.raises(ConfigError, match="unknown backend"):
        rasterize(gaussians, camera, features, backend="optix")
