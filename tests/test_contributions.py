"""Ray contributions (3DGRT response, paper eq. 1-2) against the every-ray-every-Gaussian reference
(matspray.render.raster.reference.trace_rays)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from matspray.gaussians import Gaussians
from matspray.render.raster.rasterize import rasterize
from matspray.render.raster.reference import Hit, trace_rays
from matspray.render.rays.contributions import contributions, iter_contributions
from matspray.render.settings import RasterSettings
from tests.test_rasterize import random_scene


def as_hits(c) -> list[list[Hit]]:
    """Contributions as reference.trace_rays returns them: per ray, its hits front to back."""
    hits = [[] for _ in range(c.num_rays)]
    for ray, i, alpha, weight, depth in zip(
        *(t.tolist() for t in (c.sample_ids, c.gaussian_ids, c.alphas, c.weights, c.depths))
    ):
        hits[ray].append(Hit(i, alpha, weight, depth))
    return hits


def assert_same_hits(got: list[list[Hit]], expected: list[list[Hit]], atol=1e-6):
    assert len(got) == len(expected)
    for ray, (mine, theirs) in enumerate(zip(got, expected)):
        assert [h.gaussian for h in mine] == [h.gaussian for h in theirs], f"ray {ray}"
        if theirs:
            np.testing.assert_allclose(
                np.array(mine)[:, 1:3], np.array(theirs)[:, 1:3], atol=atol, rtol=0, err_msg=f"ray {ray}"
            )
            np.testing.assert_allclose(
                np.array(mine)[:, 3], np.array(theirs)[:, 3], atol=0, rtol=1e-6, err_msg=f"ray {ray}"
            )  # float32 depth


def scene_with_awkward_gaussians(seed):
    """A random scene plus one Gaussian around the camera (its ellipsoid reaches behind the camera
    plane) and one behind the camera."""
    gaussians, camera, _ = random_scene(12, seed, width=10, height=8)
    centre = camera.center
    extra_means = torch.stack([centre + 0.3 * (torch.zeros(3) - centre) / centre.norm(), 2 * centre])
    return Gaussians(
        torch.cat([gaussians.means, extra_means]),
        torch.cat([gaussians.log_scales, torch.log(torch.tensor([[0.4, 0.3, 0.5], [0.5, 0.5, 0.5]]))]),
        torch.cat([gaussians.quats, torch.tensor([[1.0, 0.2, 0.1, 0.0], [1.0, 0.0, 0.0, 0.0]])]),
        torch.cat([gaussians.opacity_logits, torch.logit(torch.tensor([0.02, 0.9]))]),
        torch.cat([gaussians.sh, torch.zeros(2, 1, 3)]),
    ), camera


@pytest.mark.parametrize("seed,samples,falloff", [(0, 1, 1.0), (1, 2, 1.0), (2, 3, 2.0)])
def test_matches_reference(seed, samples, falloff):
    gaussians, camera = scene_with_awkward_gaussians(seed)
    c = contributions(gaussians, camera, samples, falloff=falloff)
    expected = trace_rays(gaussians, camera, samples, falloff=falloff)
    assert sum(1 for hits in expected if hits) > 20
    assert_same_hits(as_hits(c), expected)
    assert any(12 in [h.gaussian for h in hits] for hits in expected)  # the Gaussian around the camera is hit


def test_weights_sum_to_one_minus_transmittance():
    """Exact: per ray, the weights sum to 1 - prod(1 - alpha_max) over the hits returned."""
    gaussians, camera, _ = random_scene(120, 4, width=12, height=10)
    c = contributions(gaussians, camera, 2)
    alpha = c.ray_alpha().double()
    log_keep = torch.zeros(c.num_rays, dtype=torch.float64).index_add_(0, c.sample_ids, torch.log1p(-c.alphas.double()))
    torch.testing.assert_close(alpha, 1 - torch.exp(log_keep), atol=1e-6, rtol=0)
    assert alpha.max() > 0.99 and torch.bincount(c.sample_ids).max() > 20  # deep, saturated rays
    assert (c.weights > 0).all() and (c.alphas >= 1 / 255).all() and (c.alphas <= 0.99).all()
    # hits are grouped by ray and front to back
    same_ray = c.sample_ids[1:] == c.sample_ids[:-1]
    assert (c.sample_ids[1:] >= c.sample_ids[:-1]).all() and (c.depths[1:][same_ray] >= c.depths[:-1][same_ray]).all()


def test_agrees_with_rasterized_alpha():
    """The 3DGRT response is exact along each ray; the splat is the EWA approximation: the projection
    linearised at each Gaussian's centre, a 0.3 px^2 low-pass filter, blending ordered by centre depth.

    Without the filter the only differences are the linearisation, of order (extent / distance)^2 (here
    3 sigma ~ 0.1-0.5 at distance ~4: a few percent of a footprint's alpha) and the order of overlapping
    hits, so they agree within 0.03 per pixel. The filter adds 0.3 px^2 to the variance of footprints of
    a few px^2 without lowering their opacity, so splat coverage is larger by several percent: both
    agree on average to within 10% of the covered alpha, the splats never covering less."""
    gaussians, camera, _ = random_scene(25, 7, width=40, height=32)
    ray_alpha = contributions(gaussians, camera, 1).pixel_alpha()
    unfiltered = rasterize(gaussians, camera, torch.zeros(len(gaussians), 0), settings=RasterSettings(eps2d=0.0)).alpha
    filtered = rasterize(gaussians, camera, torch.zeros(len(gaussians), 0)).alpha
    assert ray_alpha.max() > 0.9 and (ray_alpha == 0).any()
    assert (ray_alpha - unfiltered).abs().max() < 0.03
    assert (ray_alpha - unfiltered).abs().mean() < 0.005
    excess = (filtered - ray_alpha).mean()
    assert 0 < excess < 0.1 * filtered.mean()


def test_bands_and_parts_cover_all_rays_once():
    gaussians, camera, _ = random_scene(30, 8, width=12, height=10)
    whole = contributions(gaussians, camera, 2)
    parts = list(iter_contributions(gaussians, camera, 2, max_samples=64))
    assert len(parts) > 3
    banded = type(whole).concatenate(parts)
    assert_same_hits(as_hits(banded), as_hits(whole), atol=1e-7)
    pixel_rows = [torch.div(p.pixel_ids, 12, rounding_mode="floor") for p in parts if len(p)]
    assert all(a.max() < b.min() for a, b in zip(pixel_rows, pixel_rows[1:]))  # disjoint bands, in order


def test_flat_gaussians_stay_exact():
    """A Gaussian 1e-4 thin (as geometry training makes them) seen at a slant: eq. (2) in the whitened
    frame must not lose precision."""
    n = 1
    gaussians = Gaussians(
        torch.zeros(n, 3),
        torch.log(torch.tensor([[0.3, 0.2, 1e-4]])),
        torch.tensor([[0.9, 0.3, 0.2, 0.1]]),
        torch.logit(torch.tensor([0.8])),
        torch.zeros(n, 1, 3),
    )
    _, camera, _ = random_scene(1, 0, width=10, height=8)
    assert_same_hits(as_hits(contributions(gaussians, camera, 2)), trace_rays(gaussians, camera, 2), atol=1e-6)


def test_rejects_bad_arguments():
    gaussians, camera, _ = random_scene(3, 0)
    with pytest.raises(ValueError, match="samples_per_side"):
        contributions(gaussians, camera, 0)
    with pytest.raises(ValueError, match="falloff"):
        contributions(gaussians, camera, 1, falloff=0.0)
