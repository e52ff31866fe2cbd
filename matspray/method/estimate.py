"""How long `matspray run` will take, said before it starts: each stage's work, in a unit its time grows with, times a
rate measured on the reference machine (2 free CPU cores, numba rasterizer). The rates come from `python -m
benchmarks.estimate RUN...` on finished runs (docs/dev/demo-time.md, "Time estimates", has the runs, the rates and how
far each estimate was from the time taken). Objects differ (how many Gaussians the geometry grows, how much of a view
they cover), so the estimate is a range of about 2x each way, not a promise; a GPU has no measured rate yet."""

from __future__ import annotations

import math
from dataclasses import dataclass

# seconds per unit of work with 2 free cores: the demo of `make demo` alone on the reference machine
# (docs/dev/demo-time.md, "Time estimates"; runs that shared the cores with other jobs took 2 to 5 times longer)
CPU_RATES = {
    "points": 7.5e-7,  # per (training view x pixel of the photos given to feature extraction)
    "geometry": 3.0e-6,  # per (iteration x pixel of a geometry view)
    "masks": 1.0e-6,  # per (training view x pixel)
    "lift": 4.3e-6,  # per ray
    "refine": 8.9e-6,  # per (iteration x pixel of a training view), each variant that merges 2D maps
    "refine-mapless": 3.8e-6,  # the same for each variant without 2D maps (no merger to train)
}
SPREAD = 2.0  # the range said: estimate / SPREAD to estimate * SPREAD


@dataclass(frozen=True)
class Work:
    """What a run's stages will do, in units their time grows with. Stages already finished are left out (0)."""

    points: float = 0.0  # training views x pixels of their photos for features (captures triangulating points only)
    geometry: float = 0.0  # iterations x pixels of one geometry view
    masks: float = 0.0  # training views x pixels (runs without masks only)
    lift: float = 0.0  # rays: training views x pixels x rays per pixel
    refine: float = 0.0  # variants that merge 2D maps, summed: iterations x pixels of one training view
    refine_mapless: float = 0.0  # the same for the variants without 2D maps

    def stages(self) -> dict[str, float]:
        return {
            "points": self.points,
            "geometry": self.geometry,
            "masks": self.masks,
            "lift": self.lift,
            "refine": self.refine,
            "refine-mapless": self.refine_mapless,
        }


def view_pixels(width: int, height: int, long_side: int = 0) -> float:
    """Pixels of a width x height view brought to `long_side` (0 or larger than the view: as it is)."""
    factor = min(1.0, long_side / max(width, height)) if long_side else 1.0
    return round(width * factor) * round(height * factor)


def feature_sizes(views: list[tuple[int, int]], downscale: float, max_size: int) -> list[tuple[int, int]]:
    """The sizes of the photos the `points` stage extracts features from: the working-size `views` [(width, height)]
    as loaded (times `downscale`), brought to at most `max_size` on their long side."""
    sizes = []
    for width, height in views:
        w, h = width * downscale, height * downscale
        factor = min(1.0, max_size / max(w, h))
        sizes.append((round(w * factor), round(h * factor)))
    return sizes


def run_work(
    views: list[tuple[int, int]],
    geometry_iterations: int,
    geometry_resolution: int,
    rays_per_pixel: int,
    refine_iterations: list[tuple[int, bool]],
    unmasked: bool,
    done: frozenset[str] = frozenset(),
    feature_views: list[tuple[int, int]] = (),
) -> Work:
    """The work of a run on training views of sizes `views` [(width, height)], refining variants of
    `refine_iterations` [(iterations, merges 2D maps)], with the stages in `done` skipped. `feature_views`: the sizes
    of the photos a capture without points extracts features from (none: no `points` stage)."""
    if not views:
        return Work()
    pixels = sum(w * h for w, h in views) / len(views)
    geometry_pixels = sum(view_pixels(w, h, geometry_resolution) for w, h in views) / len(views)
    return Work(
        points=0.0 if "points" in done else float(sum(w * h for w, h in feature_views)),
        geometry=0.0 if "geometry" in done else geometry_iterations * geometry_pixels,
        masks=len(views) * pixels if unmasked and "masks" not in done else 0.0,
        lift=0.0 if "lift" in done else len(views) * pixels * rays_per_pixel,
        refine=sum(iterations * pixels for iterations, maps in refine_iterations if maps),
        refine_mapless=sum(iterations * pixels for iterations, maps in refine_iterations if not maps),
    )


def estimate_seconds(work: Work, device_type: str) -> dict[str, float] | None:
    """Seconds per stage on the reference machine; None on a device without a measured rate (CUDA)."""
    if device_type != "cpu":
        return None
    seconds = {stage: units * CPU_RATES[stage] for stage, units in work.stages().items() if units}
    if "refine-mapless" in seconds:  # said as one stage
        seconds["refine"] = seconds.get("refine", 0.0) + seconds.pop("refine-mapless")
    return seconds


def minutes(seconds: float) -> str:
    if seconds < 1:
        return "<1 s"
    return f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"


def estimate_line(work: Work, device_type: str) -> str:
    """One line for the start of a run: the expected range and the largest stages."""
    seconds = estimate_seconds(work, device_type)
    if seconds is None:
        return "estimate: no measured rate for this device yet (the CPU rates are from 2 cores; a GPU takes far less)"
    total = sum(seconds.values())
    if total == 0:
        return "estimate: every stage is done already"
    parts = ", ".join(f"{stage} ~{minutes(s)}" for stage, s in sorted(seconds.items(), key=lambda kv: -kv[1]))
    low, high = total / SPREAD, total * SPREAD
    return (
        f"estimate: {minutes(low)} to {minutes(high)} with 2 free CPU cores ({parts}; "
        "other jobs on the cores make it longer)"
    )


def estimate_error(estimated: float, taken: float) -> float:
    """How far an estimate was from the time taken, as a factor >= 1 (2 = twice or half)."""
    if estimated <= 0 or taken <= 0:
        return math.inf
    return max(estimated / taken, taken / estimated)
