"""`matspray demo --preset paper` on one GPU, projected stage by stage and variant by variant.

    python -m benchmarks.paper_projection [--rates FILE] [--json FILE]

What the preset runs is read from the code, not listed here: the object's size (`presets.DEMO_SIZES`), the
geometry schedule (`build_config("paper").geometry`), the stages of `batch.objects.run_one_object` (predict,
geometry, lift, the frozen views, refine per variant, eval) and the variants `batch.demo.run_demo` refines
(`variants_for_maps(PAPER_VARIANTS, has_maps=True)`); which of them share a light warm-up is found by the code's own
key (`refine.warm_up_key`) on a tiny object.

Each term says what it was measured on:
  - "H200": the committed figures of one NVIDIA H200 in docs/dev/gpu.md (`H200` below, each with its table), or
    the rates of a `benchmarks.unit_rates --json` file given with `--rates` (the same machine kind, named there);
  - "CPU here": measured by this script on this machine at small sizes, used only as a ratio or scaled: how the
    merger's step time grows with the views, each variant's step against `full`'s in operations dispatched (a launch
    each on a GPU, where a step waits on its launches), how many light warm-ups refine runs, proj-average's stage;
  - a model joins them, stated with each term. The total is PROJECTED, not measured.

The Gaussian count on the paper's schedule is not measured (no run of 30 000 steps has been made): the geometry,
lifting, refinement and frozen-view terms are given for two count curves, both starting at the preset's
`init_points` and changing linearly from `densify_from` to `densify_until`, flat after: to the count the stretched
7 000-step H200 run ended with (78 391), and to the cap (`max_gaussians`, 1 000 000).
"""

from __future__ import annotations

import argparse
import inspect
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from matspray.method.config import build_config
from matspray.method.merger import MergerConfig
from matspray.presets import DEMO_SIZES, get_variant, variants_for_maps

# docs/dev/gpu.md, one NVIDIA H200 (2026-11-27); the table each comes from in the comment
H200 = {
    # "Where the time goes": a Gaussian Splatting step after densification, wall and its kernels' sum, at this count
    "geometry_profile_gaussians": 93_459,
    "geometry_profile_kernels_s": 3.11e-3,
    # "Where the time goes", second table: Gaussian Splatting 7 000 steps (stretched schedule), refinement, warm-up,
    # lifting, all on 76 172 Gaussians of the 12-view 512 px object
    "geometry_rate": 135.9,
    "rates_gaussians": 76_172,
    "refine_rate": 109.4,
    "warmup_rate": 289.6,
    "lift_s_per_view": 0.559,
    "rates_views": 12,
    # "After the change a refinement step is 10.0 ms, of which the kernels are about half", the merger's weight
    # gradient 0.9 ms of it (the largest kernel)
    "refine_kernel_share": 0.5,
    "merger_weight_gradient_s": 0.9e-3,
    # "Refinement as CUDA graphs": the stretched 7 000-step run's final count
    "stretched_final_gaussians": 78_391,
    # "Measured on one NVIDIA H200 (2026-11-26)", the demo preset with gsplat on a 128 px object with 40 training and
    # 10 test views, 3 variants: predictions 0.9 s; the whole run 101 s, of which its listed stages 90.2 s
    "demo_predict_s": 0.9,
    "demo_views": 40,
    "demo_resolution": 128,
    "demo_unlisted_s": 101 - (0.9 + 47.9 + 4.4 + 20.4 + 0.0 + 16.6),
    "demo_test_views": 10,
    "demo_variants": 3,
}


@dataclass(frozen=True)
class Term:
    stage: str
    seconds: float
    source: str  # what it was measured on, and the model that scales it


# ------------------------------------------------------------------------------------------ what the preset runs
def paper_variants() -> tuple[str, ...]:
    """The variants `matspray demo --preset paper` refines: `run_object`'s default, which `run_demo` calls it with,
    as `run_one_object` resolves them for a run with 2D maps (the simulated predictor's)."""
    from matspray.batch.demo import run_object

    return variants_for_maps(inspect.signature(run_object).parameters["variants"].default, has_maps=True)


def count_curve(steps: int, start: int, end: int, densify_from: int, densify_until: int) -> torch.Tensor:
    """Gaussians at each step [steps]: `start` until `densify_from`, linear to `end` at `densify_until`, then flat."""
    s = torch.arange(steps, dtype=torch.float64)
    ramp = ((s - densify_from) / max(densify_until - densify_from, 1)).clamp(0, 1)
    return start + (end - start) * ramp


def geometry_seconds(counts: torch.Tensor) -> float:
    """The sum over steps of t(N) = T0 + k N: k from the H200 profile's kernel time per Gaussian, T0 so that the
    model gives the measured 7 000-step rate at its count (the launches and Python, which do not grow with N)."""
    k = H200["geometry_profile_kernels_s"] / H200["geometry_profile_gaussians"]
    t0 = 1.0 / H200["geometry_rate"] - k * H200["rates_gaussians"]
    return float((t0 + k * counts).sum())


# ------------------------------------------------------------------------------------------ CPU measurements
def merger_timer(views: int, gaussians: int):
    """A function timing one forward and backward of the `full` source (the Neural Merger) for `views` views."""
    from matspray.method.refine.loop import material_source

    g = torch.Generator().manual_seed(0)
    means = torch.rand(gaussians, 3, generator=g)
    values = torch.rand(gaussians, views, 5, generator=g)
    seen = torch.rand(gaussians, views, generator=g) > 0.3
    bounds = torch.tensor([[0.0] * 3, [1.0] * 3])
    source = material_source(get_variant("full"), means, values, seen, bounds, MergerConfig())
    source().sum().backward()  # first call: allocations

    def timed() -> float:
        start = time.perf_counter()
        source().sum().backward()
        return time.perf_counter() - start

    return timed


def merger_view_scaling(views=(6, 12, 25, 50, 100), gaussians: int = 2000, repeats: int = 5) -> dict:
    """The merger's CPU step seconds at each view count (the least of `repeats`, the counts taken in turn so that a
    busy spell of the machine falls on all of them), and the least-squares line a + b V through them."""
    timers = [merger_timer(v, gaussians) for v in views]
    seconds = [min(found) for found in zip(*[[timer() for timer in timers] for _ in range(repeats)])]
    x = torch.tensor(views, dtype=torch.float64)
    y = torch.tensor(seconds, dtype=torch.float64)
    b = float(((x - x.mean()) * (y - y.mean())).sum() / ((x - x.mean()) ** 2).sum())
    a = float(y.mean() - b * x.mean())
    return {"views": list(views), "seconds": seconds, "a": a, "b": b, "gaussians": gaussians}


def tiny_inputs(points: int):
    from benchmarks.step_cost import refine_inputs

    return refine_inputs(torch.device("cpu"), points=points)


def variant_step_ratios(variants, points: int = 300, short: int = 2, long: int = 5) -> dict[str, float]:
    """Each trained variant's refinement step against `full`'s in operations dispatched (`benchmarks.step_cost`'s
    count, path gpu: what a CUDA device dispatches, the graphs replayed through the stand-in), on a tiny object: two
    runs that differ only in their step count, so the set-up cancels. A step on the GPU waits on its launches (one
    per operation; docs/dev/gpu.md), and a count does not move with the machine's load as a CPU time does."""
    from benchmarks.graph_replay import graph_stand_in
    from benchmarks.step_cost import as_on_a_gpu, counting
    from matspray.device import capturing_with
    from matspray.method.refine.loop import refine
    from matspray.render.backend import rendering_with

    base = build_config("paper").refine
    names = ("full", *[v for v in variants if v != "full" and get_variant(v).trains])
    operations = {}
    cpu = torch.device("cpu")
    with rendering_with("numba"), as_on_a_gpu(), capturing_with(graph_stand_in):
        inputs = tiny_inputs(points)
        for name in names:

            def run(iterations: int, name=name) -> int:
                config = replace(base, variant=name, iterations=iterations, light_warmup=1, log_every=10**9)
                with counting(cpu, without_numba=True) as count:
                    refine(inputs, config, progress=False)
                return count.operations

            run(2)  # first calls: compiled kernels, captures
            operations[name] = max(run(long) - run(short), 1) / (long - short)
    return {name: ops / operations["full"] for name, ops in operations.items()}


def light_warm_ups(variants, points: int = 300) -> int:
    """How many light warm-ups the variants run: those that learn the light, counted once per key of
    `refine.warm_up_key` (their starting materials and settings), as `refine` shares them within a run."""
    from matspray.method.refine.loop import material_source, warm_up_key

    inputs = tiny_inputs(points)
    base = build_config("paper").refine
    keys = set()
    for name in variants:
        variant = get_variant(name)
        if not variant.learns_light:
            continue
        config = replace(base, variant=name)
        means = inputs.gaussians.means.detach()
        torch.manual_seed(config.seed)
        source = material_source(variant, means, inputs.values, inputs.seen, inputs.bounds, config.merger)
        with torch.no_grad():
            keys.add(warm_up_key(source(), config))
    return len(keys)


def average_seconds(points: int = 300) -> float:
    """Seconds of `proj-average`'s refinement stage (no training: the average of the lifted values) on the CPU."""
    from matspray.method.refine.loop import refine

    inputs = tiny_inputs(points)
    config = replace(build_config("paper").refine, variant="proj-average")
    refine(inputs, config, progress=False)
    start = time.perf_counter()
    refine(inputs, config, progress=False)
    return time.perf_counter() - start


def cpu_figures(
    merger_gaussians: int = 2000,
    points: int = 300,
    short: int = 2,
    long: int = 5,
    merger_views=(6, 12, 25, 50, 100),
    repeats: int = 5,
) -> dict:
    """What this script measures on this machine's CPU (small sizes, used as ratios or scaled)."""
    variants = paper_variants()
    return {
        "merger": merger_view_scaling(merger_views, merger_gaussians, repeats),
        "variant_ratios": variant_step_ratios(variants, points, short, long),
        "warm_ups": light_warm_ups(variants, points),
        "average_seconds": average_seconds(points),
        "average_gaussians": points,
    }


# ------------------------------------------------------------------------------------------ the projection
def refine_step_seconds(rates: dict, gaussians: float, views: int, merger: dict | None, rate_key: str) -> float:
    """A refinement (or warm-up) step at `gaussians` and `views`: the H200 step split into launches (constant) and
    kernels (grown with the count), the merger's kernels (3 x its weight gradient: forward, input and weight
    gradient products of one size) grown with the views as its CPU step grows (a + b V)."""
    step = 1.0 / rates[rate_key]
    share = rates["refine_kernel_share"]
    scale = gaussians / rates["rates_gaussians"]
    seconds = step * (1 - share) + step * share * scale
    if merger is not None:
        at = lambda v: merger["a"] + merger["b"] * v  # noqa: E731
        merger_s = 3 * rates["merger_weight_gradient_s"] * scale
        seconds += merger_s * (at(views) / at(rates["rates_views"]) - 1)
    return seconds


def project(
    cpu: dict, final_gaussians: int, rates: dict = H200, rates_from: str = "H200 (docs/dev/gpu.md)"
) -> list[Term]:
    """Every stage and variant of `demo --preset paper`, in seconds on one GPU, for the count curve ending at
    `final_gaussians`."""
    size = DEMO_SIZES["paper"]
    run = build_config("paper")
    geometry, refine_config = run.geometry, run.refine
    counts = count_curve(
        geometry.iterations, geometry.init_points, final_gaussians, geometry.densify_from, geometry.densify_until
    )
    n = final_gaussians
    curve = f"count {geometry.init_points} -> {n} over steps {geometry.densify_from}-{geometry.densify_until}"
    pixels = size.views * size.res**2 / (rates["demo_views"] * rates["demo_resolution"] ** 2)
    terms = [
        Term(
            "predict (simulated, %d views)" % size.views,
            rates["demo_predict_s"] * pixels,
            f"{rates_from}: the demo run's predictions, scaled by views x pixels",
        ),
        Term(
            f"geometry ({geometry.iterations} steps)",
            geometry_seconds(counts),
            f"{rates_from}: t(N) = T0 + kN (profile's kernels per Gaussian, the 7 000-step rate), summed over the "
            f"{curve}",
        ),
        Term(
            f"lift ({size.views} views, {run.lift.samples_per_side}x{run.lift.samples_per_side} rays)",
            size.views * rates["lift_s_per_view"] * n / rates["rates_gaussians"],
            f"{rates_from}: s per 512 px view, grown with the count ({n})",
        ),
    ]
    step = refine_step_seconds(rates, n, size.views, cpu["merger"], "refine_rate")
    terms.append(Term(f"frozen views ({size.views})", size.views * step,
                      f"{rates_from}: one refinement step per view (a render and its backward: an upper bound of one "
                      "render)"))  # fmt: skip
    merger = cpu["merger"]
    warm = refine_step_seconds(rates, n, size.views, None, "warmup_rate")
    warm_source = (
        f"{rates_from}: warm-up rate, grown with the count; {cpu['warm_ups']} warm-up(s) by refine's key (CPU here)"
    )
    terms.append(Term(f"light warm-up x{cpu['warm_ups']} ({refine_config.light_warmup} steps)",
                      cpu["warm_ups"] * refine_config.light_warmup * warm, warm_source))  # fmt: skip
    for name in paper_variants():
        variant = get_variant(name)
        if not variant.trains:
            seconds = cpu["average_seconds"] * n / cpu["average_gaussians"]
            terms.append(Term(f"refine [{name}]", seconds, "CPU here: the stage at a tiny size, grown with the count"))
            continue
        uses_merger = variant.source == "merger"
        ratio = cpu["variant_ratios"][name]
        seconds = (
            refine_config.iterations
            * ratio
            * refine_step_seconds(rates, n, size.views, merger if uses_merger else None, "refine_rate")
        )
        how = f"{rates_from}: `full`'s rate at {n} Gaussians"
        how += f", the merger at {size.views} views (its CPU step a + bV)" if uses_merger else ""
        how += (
            f", x{ratio:.2f} (its step's operations against full's, counted on the CPU here)" if name != "full" else ""
        )
        terms.append(Term(f"refine [{name}] ({refine_config.iterations} steps)", seconds, how))
    per_view = rates["demo_unlisted_s"] / (rates["demo_test_views"] * rates["demo_variants"])
    variants = len(paper_variants())
    evaluated = per_view * size.test_views * variants
    terms.append(Term(f"eval ({size.test_views} test views x {variants} variants)", evaluated,
                      f"{rates_from}: the demo run's seconds outside its listed stages per test view and variant "
                      f"(an upper bound of its evaluation), the same per view at 512 px; pixel-bound it would be "
                      f"x{(size.res / rates['demo_resolution']) ** 2:.0f}"))  # fmt: skip
    return terms


def report(terms: list[Term], final_gaussians: int) -> str:
    lines = [f"demo --preset paper on one GPU, count curve to {final_gaussians} Gaussians:"]
    for term in terms:
        lines.append(f"  {term.stage:<44} {term.seconds:9.1f} s   [{term.source}]")
    lines.append(f"  {'TOTAL, PROJECTED (not measured)':<44} {sum(t.seconds for t in terms):9.1f} s")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", type=Path, help="write the terms and the CPU figures here")
    args = parser.parse_args()
    cpu = cpu_figures()
    merger = cpu["merger"]
    print("merger step on the CPU (%d Gaussians): " % merger["gaussians"]
          + ", ".join(f"{v} views {s * 1e3:.1f} ms" for v, s in zip(merger["views"], merger["seconds"]))
          + f"; a + bV with a = {merger['a'] * 1e3:.2f} ms, b = {merger['b'] * 1e3:.3f} ms per view")  # fmt: skip
    print("variant steps against full's (CPU): " + ", ".join(f"{k} {v:.2f}" for k, v in cpu["variant_ratios"].items()))
    results = {"cpu": cpu}
    max_gaussians = build_config("paper").geometry.max_gaussians
    for final in (H200["stretched_final_gaussians"], max_gaussians):
        terms = project(cpu, final)
        print(report(terms, final))
        results[str(final)] = [asdict(t) for t in terms]
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
