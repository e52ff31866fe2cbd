"""benchmarks/material_bias.py: the signed, absolute and RMS error on the object."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.material_bias import error_stats, scalar_map
from matspray.eval.run_eval import GroundTruth


def truth(roughness, mask):
    h, w = roughness.shape
    return GroundTruth(
        mask=mask, basecolor=torch.zeros(h, w, 3), roughness=roughness, metallic=torch.zeros(h, w), relit={}
    )


def test_error_stats_count_only_the_object_and_keep_the_sign():
    mask = torch.tensor([[1.0, 1.0], [0.0, 0.6]])
    t = truth(torch.full((2, 2), 0.5), mask)
    pred = torch.tensor([[0.3, 0.4], [0.9, 0.8]])  # errors on the object: -0.2, -0.1, +0.3; off it +0.4
    stats = error_stats([pred], [t], "roughness")
    assert stats["signed"] == pytest.approx(0.0, abs=1e-7)
    assert stats["abs"] == pytest.approx(0.2, abs=1e-7)
    assert stats["rmse"] == pytest.approx(math.sqrt((0.04 + 0.01 + 0.09) / 3), abs=1e-7)


def test_error_stats_pool_the_views_pixels_not_their_means():
    full, small = torch.ones(2, 2), torch.tensor([[1.0, 0.0], [0.0, 0.0]])
    views = [truth(torch.zeros(2, 2), full), truth(torch.zeros(2, 2), small)]
    stats = error_stats([torch.full((2, 2), 0.1), torch.full((2, 2), 0.5)], views, "roughness")
    assert stats["signed"] == pytest.approx((4 * 0.1 + 0.5) / 5)  # 5 object pixels, not the mean of 0.1 and 0.5


def test_base_colour_is_the_mean_over_rgb_whichever_name_the_maps_use():
    class Renders:  # the asset renders name it base_color; truths and predictions basecolor
        base_color = torch.tensor([[[0.0, 0.3, 0.6]]])

    assert float(scalar_map(Renders(), "basecolor")) == pytest.approx(0.3)
    assert float(scalar_map(truth(torch.zeros(1, 1), torch.ones(1, 1)), "roughness")) == 0.0
