"""benchmarks.metallic_parts: the parts of a view are disjoint, cover the object, and sit where the definitions say;
the figures add up."""

import math

import torch

from benchmarks.metallic_parts import metallic_parts, part_figures, squared_errors


def square_object():
    """One 12 x 12 view: an 8 x 8 object (rows and columns 2..9), metal on its right half (columns >= 6)."""
    mask = torch.zeros(1, 12, 12)
    mask[:, 2:10, 2:10] = 1.0
    truth = torch.zeros(1, 12, 12)
    truth[:, 2:10, 6:10] = 1.0
    return truth, mask


def test_parts_are_disjoint_cover_the_object_and_lie_where_defined():
    truth, mask = square_object()
    parts = metallic_parts(truth, mask, radius=1)
    total = sum(p.long() for p in parts.values())
    assert torch.equal(total, (mask > 0).long())  # each object pixel in exactly one part, nothing off the object
    # the silhouette: object pixels within 1 px of the outline (the ring of rows / columns 2 and 9)
    ring = (mask > 0) & ~torch.nn.functional.pad(torch.ones(1, 6, 6, dtype=torch.bool), (3, 3, 3, 3))
    assert torch.equal(parts["silhouette"], ring)
    # the edge: inside the ring, the columns next to the metal boundary (5 and 6)
    edge = torch.zeros(1, 12, 12, dtype=torch.bool)
    edge[:, 3:9, 5:7] = True
    assert torch.equal(parts["edge"], edge)
    assert bool((truth[parts["interior metal"]] == 1).all()) and bool((truth[parts["interior dielectric"]] == 0).all())


def test_part_figures_share_the_pooled_error():
    truth, mask = square_object()
    parts = metallic_parts(truth, mask, radius=1)
    pred = truth.clone()
    pred[parts["edge"]] = 0.5  # all the error on the edge
    errors = squared_errors(pred, truth, mask)
    figures = part_figures(errors, parts)
    assert math.isclose(figures["psnr"], -10 * math.log10(12 * 0.25 / 144))  # 12 edge pixels off by 0.5, of 144
    assert math.isclose(figures["edge"]["error"], 1.0) and figures["edge"]["gain"] == math.inf
    assert math.isclose(figures["edge"]["psnr"], -10 * math.log10(0.25))
    assert figures["interior metal"]["error"] == 0.0 and figures["interior metal"]["gain"] == 0.0
    assert math.isclose(sum(figures[p]["pixels"] for p in parts), 1.0)
    assert math.isclose(figures["view_mean"], figures["psnr"])  # one view: both poolings agree
