"""Pixel enumeration of ellipses and boxes against dense point tests."""

from __future__ import annotations

import torch

from matspray.render.pairs import box_pixel_pairs, clip_rows, ellipse_pixel_pairs, pixel_boxes, row_bands

WIDTH, HEIGHT = 23, 17


def random_ellipses(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([WIDTH + 6.0, HEIGHT + 6.0]) - 3
    angle = torch.rand(n, generator=g, dtype=torch.float64) * 3.2
    sx, sy = (
        0.2 + 4 * torch.rand(n, generator=g, dtype=torch.float64),
        0.2 + 2 * torch.rand(n, generator=g, dtype=torch.float64),
    )
    c, s = torch.cos(angle), torch.sin(angle)
    cov = torch.stack([c * c * sx**2 + s * s * sy**2, c * s * (sx**2 - sy**2), s * s * sx**2 + c * c * sy**2], -1)
    det = cov[:, 0] * cov[:, 2] - cov[:, 1] ** 2
    conics = torch.stack([cov[:, 2], -cov[:, 1], cov[:, 0]], -1) / det[:, None]
    radius2 = 1 + 8 * torch.rand(n, generator=g, dtype=torch.float64)
    half = torch.sqrt(radius2[:, None] * cov[:, [0, 2]])
    return centres, conics, radius2, half


def inside(points, centre, conic, radius2):  # [P, 2] -> [P] bool
    d = points - centre
    return conic[0] * d[:, 0] ** 2 + 2 * conic[1] * d[:, 0] * d[:, 1] + conic[2] * d[:, 1] ** 2 <= radius2


def as_set(owner, pixel_ids):
    return set(zip(owner.tolist(), pixel_ids.tolist()))


def test_centre_mode_lists_exactly_the_pixels_whose_centre_is_inside():
    centres, conics, radius2, half = random_ellipses()
    boxes = pixel_boxes(centres - half, centres + half, WIDTH, HEIGHT, centres=True)
    got = as_set(*ellipse_pixel_pairs(boxes, centres, conics, radius2, WIDTH))
    ys, xs = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    pixel_centres = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).double() + 0.5
    expected = {
        (i, p)
        for i in range(len(centres))
        for p in torch.nonzero(inside(pixel_centres, centres[i], conics[i], radius2[i])).flatten().tolist()
    }
    assert got == expected and len(expected) > 100


def test_area_mode_lists_every_pixel_the_ellipse_touches():
    """A superset of the pixels holding any of 8 x 8 dense samples inside the ellipse, and not much more."""
    centres, conics, radius2, half = random_ellipses(seed=1)
    boxes = pixel_boxes(centres - half, centres + half, WIDTH, HEIGHT, centres=False)
    got = as_set(*ellipse_pixel_pairs(boxes, centres, conics, radius2, WIDTH, touch="area"))
    s = 8
    ys, xs = torch.meshgrid(torch.arange(HEIGHT * s), torch.arange(WIDTH * s), indexing="ij")
    samples = (torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).double() + 0.5) / s
    pixel_of = (ys.reshape(-1) // s) * WIDTH + xs.reshape(-1) // s
    touched = {
        (i, p)
        for i in range(len(centres))
        for p in pixel_of[inside(samples, centres[i], conics[i], radius2[i])].unique().tolist()
    }
    assert touched <= got
    assert len(got) < 1.15 * len(touched)
    in_boxes = as_set(*box_pixel_pairs(boxes, WIDTH))
    assert got <= in_boxes and len(got) < 0.9 * len(in_boxes)


def test_row_bands_split_the_work_and_cover_every_row():
    centres, conics, radius2, half = random_ellipses(seed=2)
    boxes = pixel_boxes(centres - half, centres + half, WIDTH, HEIGHT, centres=True)
    bands = row_bands(boxes, HEIGHT, budget=60)
    assert bands[0][0] == 0 and bands[-1][1] == HEIGHT and len(bands) > 3
    assert all(a[1] == b[0] for a, b in zip(bands, bands[1:]))
    whole = as_set(*box_pixel_pairs(boxes, WIDTH))
    parts = [as_set(*box_pixel_pairs(clip_rows(boxes, r0, r1), WIDTH)) for r0, r1 in bands]
    assert set().union(*parts) == whole and sum(map(len, parts)) == len(whole)
