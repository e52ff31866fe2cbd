"""Candidate (Gaussian, pixel) pairs, enumerated row span by row span, and row bands that bound memory.

A box is (x0, y0, x1, y1) in inclusive pixel indices; x1 < x0 or y1 < y0 means empty. Pixel ids are
row-major over the whole image: id = row * width + column.
"""

from __future__ import annotations

import torch
from torch import Tensor

EMPTY_BOX = (0, 0, -1, -1)
_CONSTANTS: dict[tuple, Tensor] = {}


def constant(values: tuple, device, dtype=torch.long) -> Tensor:  # -> [len(values)]
    """`torch.tensor(values)` on `device`, made once per device and dtype: on a GPU, a tensor made from Python numbers
    is a copy that waits for every queued kernel, each time."""
    key = (tuple(values), str(device), dtype)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor(values, device=device, dtype=dtype)
    return _CONSTANTS[key]


def pixel_boxes(
    lo: Tensor,  # [N, 2] smallest continuous (x, y) a pixel must reach
    hi: Tensor,  # [N, 2] largest continuous (x, y)
    width: int,
    height: int,
    centres: bool,
) -> Tensor:  # [N, 4] long (x0, y0, x1, y1), clipped to the image
    """Pixels whose centre (centres=True) or whose area (centres=False) meets the box [lo, hi]."""
    if centres:  # centre i + 0.5 in [lo, hi]
        first, last = torch.ceil(lo - 0.5), torch.floor(hi - 0.5)
    else:  # area [i, i + 1) meets [lo, hi]
        first, last = torch.floor(lo), torch.floor(hi)
    size = constant((width, height), lo.device, lo.dtype)
    first = torch.maximum(first, torch.zeros_like(first))
    last = torch.minimum(last, size - 1)
    finite = torch.isfinite(lo).all(dim=-1) & torch.isfinite(hi).all(dim=-1)
    empty = ~((first <= last).all(dim=-1) & finite)
    boxes = torch.cat([first, last], dim=-1).nan_to_num(0.0)
    boxes = torch.where(empty[:, None], constant(EMPTY_BOX, lo.device, lo.dtype), boxes)
    return boxes.long()


def box_areas(boxes: Tensor) -> Tensor:  # [N, 4] -> [N] number of pixels (0 when empty)
    w = (boxes[:, 2] - boxes[:, 0] + 1).clamp_min(0)
    h = (boxes[:, 3] - boxes[:, 1] + 1).clamp_min(0)
    return w * h


def row_bands(boxes: Tensor, height: int, budget: int) -> list[tuple[int, int]]:
    """Split image rows into bands [r0, r1) that each hold about `budget` (box, pixel) pairs.

    A single row holding more than `budget` pairs becomes a band of its own.
    """
    widths = (boxes[:, 2] - boxes[:, 0] + 1).clamp_min(0)
    nonempty = (widths > 0) & (boxes[:, 3] >= boxes[:, 1])
    diff = torch.zeros(height + 1, dtype=torch.long, device=boxes.device)
    diff.index_add_(0, boxes[nonempty, 1], widths[nonempty])
    diff.index_add_(0, boxes[nonempty, 3] + 1, -widths[nonempty])
    per_row = torch.cumsum(diff, 0)[:height].tolist()
    bands, start, total = [], 0, 0
    for row, count in enumerate(per_row):
        if total > 0 and total + count > budget:
            bands.append((start, row))
            start, total = row, 0
        total += count
    bands.append((start, height))
    return bands


def clip_rows(boxes: Tensor, row_start: int, row_end: int) -> Tensor:  # [N, 4] -> [N, 4] within rows [start, end)
    clipped = boxes.clone()
    clipped[:, 1] = clipped[:, 1].clamp_min(row_start)
    clipped[:, 3] = clipped[:, 3].clamp_max(row_end - 1)
    return clipped


def box_rows(boxes: Tensor) -> tuple[Tensor, Tensor]:
    """One entry per (box, row): owner [R] and row index [R]."""
    heights = (boxes[:, 3] - boxes[:, 1] + 1).clamp_min(0)
    heights = torch.where(boxes[:, 2] >= boxes[:, 0], heights, torch.zeros_like(heights))
    first = torch.cumsum(heights, 0) - heights
    # one host read of the total, which both expansions are told (each would read it again on a GPU, a wait each)
    total = int(first[-1] + heights[-1]) if len(boxes) else 0
    owner = torch.repeat_interleave(torch.arange(len(boxes), device=boxes.device), heights, output_size=total)
    rows = torch.arange(total, device=boxes.device) + torch.repeat_interleave(
        boxes[:, 1] - first, heights, output_size=total
    )
    return owner, rows


def expand_spans(
    owner: Tensor,  # [R] owner of each span
    rows: Tensor,  # [R] row of each span
    first: Tensor,  # [R] first column
    last: Tensor,  # [R] last column (inclusive); last < first means empty
    width: int,
) -> tuple[Tensor, Tensor]:  # owner [M], pixel id [M] of every pixel in every span
    counts = (last - first + 1).clamp_min(0)
    start = torch.cumsum(counts, 0) - counts
    total = int(start[-1] + counts[-1]) if counts.numel() else 0
    owners = torch.repeat_interleave(owner, counts, output_size=total)
    base = rows * width + first - start  # pixel id of the span's pixel k is base + (global index)
    pixel_ids = torch.arange(total, device=owner.device) + torch.repeat_interleave(base, counts, output_size=total)
    return owners, pixel_ids


def box_pixel_pairs(boxes: Tensor, width: int) -> tuple[Tensor, Tensor]:
    """Every pixel of every box: owner [M] and pixel id [M] (box-major, row-major inside a box)."""
    owner, rows = box_rows(boxes)
    return expand_spans(owner, rows, boxes[owner, 0], boxes[owner, 2], width)


def ellipse_pixel_pairs(
    boxes: Tensor,  # [N, 4] bounding boxes of the ellipses (rows to scan, columns to clip to)
    centres: Tensor,  # [N, 2] ellipse centres (x, y), pixel coordinates
    conics: Tensor,  # [N, 3] (a, b, c): the ellipse is a dx^2 + 2 b dx dy + c dy^2 <= radius2
    radius2: Tensor,  # [N]
    width: int,
    touch: str = "centre",
) -> tuple[Tensor, Tensor]:
    """Pixels whose centre (touch="centre") or whose area (touch="area") meets each ellipse:
    owner [M] and pixel id [M].

    At height dy from the centre the ellipse spans dx in [(-b dy - sqrt(D)) / a, (-b dy + sqrt(D)) / a],
    D = a radius2 - (a c - b^2) dy^2. For pixel areas, the span over a row's strip [y, y + 1] is taken
    where each side reaches furthest: the right side at the height of the rightmost point (clamped to
    the strip), the left side at the height of the leftmost point.
    """
    owner, rows = box_rows(boxes)
    a, b, c = conics.index_select(0, owner).unbind(-1)
    cx, cy = centres.index_select(0, owner).unbind(-1)
    r2 = radius2.index_select(0, owner)
    det = (a * c - b * b).clamp_min(1e-30)
    top = rows.to(a.dtype) - cy  # dy at the top of the row
    if touch == "centre":
        dy_left = dy_right = top + 0.5
    elif touch == "area":
        reach = torch.sqrt(r2 * a / det)  # half height of the ellipse
        lo, hi = torch.maximum(top, -reach), torch.minimum(top + 1.0, reach)
        dy_right = -b * torch.sqrt(r2 / (c * det))  # height of the rightmost point
        dy_left, dy_right = (
            torch.minimum(torch.maximum(-dy_right, lo), hi),
            torch.minimum(torch.maximum(dy_right, lo), hi),
        )
    else:
        raise ValueError(f"ellipse_pixel_pairs: touch must be 'centre' or 'area', got {touch!r}")

    def half_span(dy):
        return torch.sqrt((a * r2 - det * dy * dy).clamp_min(0.0)) / a

    x_lo = cx - b * dy_left / a - half_span(dy_left)
    x_hi = cx - b * dy_right / a + half_span(dy_right)
    if touch == "centre":
        first, last = torch.ceil(x_lo - 0.5), torch.floor(x_hi - 0.5)
    else:
        first, last = torch.floor(x_lo), torch.floor(x_hi)
    box = boxes.index_select(0, owner)
    first = torch.maximum(first.clamp_min(-1).long(), box[:, 0])
    last = torch.minimum(last.clamp_max(width).long(), box[:, 2])
    return expand_spans(owner, rows, first, last, width)
