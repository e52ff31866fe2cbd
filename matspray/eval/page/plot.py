"""The loss curves of refinement as an inline SVG: steps along x, the losses on a log scale along y, both axes
labelled and ticked at round values."""

from __future__ import annotations

import html
import math

COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
TERMS = {  # history key -> what the legend calls it
    "material": "2D-map loss (L1 to the 2D maps)",
    "photo": "photometric loss (0.8 L1 + 0.2 (1 - SSIM) to the photos)",
}


def nice_step(span: float, count: int) -> float:
    """The round step (1, 2 or 5 times a power of ten) nearest to cutting `span` into `count` parts."""
    raw = span / max(count, 1)
    power = 10 ** math.floor(math.log10(raw))
    return min((m * power for m in (1, 2, 5, 10)), key=lambda step: abs(math.log(step / raw)))


def linear_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """Round values from `low` to `high` (both included where they are round), about `count` of them."""
    if high <= low:
        return [low]
    step = nice_step(high - low, count)
    first = math.ceil(low / step - 1e-9)
    ticks = [k * step for k in range(first, int(math.floor(high / step + 1e-9)) + 1)]
    return [round(t, 12) for t in ticks]


def log_ticks(low: float, high: float) -> list[float]:
    """Ticks for a log axis over [low, high] (> 0): 1, 2 and 5 times the powers of ten inside it; where that gives
    fewer than three (a narrow range), round values of a linear step instead."""
    ticks = [
        m * 10**e
        for e in range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)
        for m in (1, 2, 5)
        if low * (1 - 1e-9) <= m * 10**e <= high * (1 + 1e-9)
    ]
    return ticks if len(ticks) >= 3 else [t for t in linear_ticks(low, high) if t > 0]


def tick_label(value: float) -> str:
    return f"{value:.3g}"


def loss_curves_svg(histories: dict[str, list[dict]], width: int = 640, height: int = 300) -> str:
    """Inline SVG with one polyline per (variant, loss term), the loss on a log scale over the steps, labelled axes
    with ticks, and a legend below."""
    series = []
    for variant, history in histories.items():
        for term in TERMS:
            points = [(r["step"], r[term]) for r in history if r.get(term, 0) > 0]
            if points:
                series.append((f"{variant}: {TERMS[term]}", points))
    if not series:
        return "<p><i>No loss curves (no trained variant).</i></p>"
    left, top, right, bottom = 64, 10, 16, 46  # margins around the plot: tick labels and axis titles
    plot_w, plot_h = width - left - right, height - top - bottom
    max_step = max(p[0] for _, pts in series for p in pts) or 1
    values = [p[1] for _, pts in series for p in pts]
    low, high = min(values), max(values)
    if high <= low * 1.0001:
        low, high = low / 1.1, high * 1.1
    log_low, log_high = math.log10(low), math.log10(high)

    def x(step: float) -> float:
        return left + plot_w * step / max_step

    def y(value: float) -> float:
        return top + plot_h * (log_high - math.log10(value)) / (log_high - log_low)

    parts = [
        f'<svg class="plot" width="{width}" height="{height + 18 * len(series)}" role="img" '
        'aria-label="loss curves of refinement">',
        f'<rect x="{left}" y="{top}" width="{plot_w}" height="{plot_h}" fill="none" stroke="#999"/>',
    ]
    for step in linear_ticks(0, max_step):
        parts.append(
            f'<line x1="{x(step):.1f}" y1="{top + plot_h}" x2="{x(step):.1f}" y2="{top + plot_h + 4}" stroke="#666"/>'
            f'<text x="{x(step):.1f}" y="{top + plot_h + 16}" font-size="11" text-anchor="middle">{step:g}</text>'
        )
    for value in log_ticks(low, high):
        parts.append(
            f'<line x1="{left - 4}" y1="{y(value):.1f}" x2="{left + plot_w}" y2="{y(value):.1f}" stroke="#eee"/>'
            f'<text x="{left - 6}" y="{y(value) + 4:.1f}" font-size="11" text-anchor="end">{tick_label(value)}</text>'
        )
    parts.append(
        f'<text x="{left + plot_w / 2:.0f}" y="{height - 8}" font-size="12" text-anchor="middle">refinement step</text>'
        f'<text x="14" y="{top + plot_h / 2:.0f}" font-size="12" text-anchor="middle" '
        f'transform="rotate(-90 14 {top + plot_h / 2:.0f})">loss (log scale)</text>'
    )
    for i, (label, points) in enumerate(series):
        color = COLORS[i % len(COLORS)]
        coords = " ".join(f"{x(s):.1f},{y(v):.1f}" for s, v in points)
        parts.append(f'<polyline fill="none" stroke="{color}" stroke-width="1.4" points="{coords}"/>')
        parts.append(
            f'<text x="{left}" y="{height + 12 + 18 * i}" font-size="12" fill="{color}">{html.escape(label)}</text>'
        )
    parts.append("</svg>")
    return "\n".join(parts)
