"""The method on the demo object with the simulated predictor: every variant's relighting and material
quality, the raw 2D predictions' quality, and the seconds per stage.

    python -m benchmarks.method [--preset demo|test] [--out runs/bench-method] [--shape composite] [--ceilings]
                                [--refine-iterations N] [--refine-seeds 0 1 2]

Prints one table; the figures also land in OUT/run/eval/metrics.json and OUT/run/report.html.
With several --refine-seeds every variant is refined once per seed on the same geometry and lift
(the seed sets the merger's initialisation and the order of the training views); the table then
holds the mean over the seeds, with each seed's relighting PSNR beside it, and the run folder keeps
the last seed's assets (and its seconds per stage). On the demo object the full method's relighting PSNR
spans 0.4 dB over seeds 0-2, more than the gaps between the variants: compare means.

With --ceilings it also prints what no material estimate can beat on this object:
  shading ceiling  the true G-buffer (true base color, roughness, metallic, normals and mask) shaded by
                   our split-sum renderer vs Mitsuba's path-traced relit views: the cost of the
                   shading model alone, unshadowed and shadowed by the full asset's baked visibility
                   (interreflections are never modelled);
  lifted truth     the ground-truth 2D maps lifted onto our Gaussians and averaged (proj-average with
                   the ground-truth "predictor", in OUT/run-truth, reusing the geometry): the cost of
                   the geometry, the lifting and the Gaussian representation with perfect 2D maps;
  softmax merger   the lifted truth clamped, per Gaussian and channel, to the range of what that Gaussian
                   received from the predictor (`merger.clamp_to_seen_range`): an oracle that knows the
                   truth and is held to convex combinations of the per-view values, as the Neural Merger
                   is. Where the predictor is wrong in the same direction in every view (tone-mapped
                   roughness), no softmax merger gets closer to the true materials than this (its
                   relighting is not a strict bound: a wrong value can offset another one's error).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from benchmarks.ceilings import lift_truth, read_test_truth, shading_ceiling, softmax_reach
from matspray.batch.demo import make_demo_object, run_object
from matspray.method.config import ADDITION_NAMES, METHODS, build_config
from matspray.presets import LABELS as VARIANT_LABELS
from matspray.rundir import RunDir, share_stage


def fmt(value, digits=2):
    return "—" if value is None else (f"{value:.{digits}f}" if value != float("inf") else "inf")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="demo", choices=("test", "demo"))
    parser.add_argument("--out", type=Path, default=Path("runs/bench-method"))
    parser.add_argument("--shape", default="composite")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ceilings", action="store_true", help="also measure the shading and lifted-truth ceilings")
    parser.add_argument(
        "--refine-iterations", type=int, help="override the preset's refinement iterations (earlier stages are reused)"
    )
    parser.add_argument(
        "--refine-seeds",
        type=int,
        nargs="+",
        help="refine every variant once per seed and report the means (default: the object's seed)",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="matspray",
        help="the method (default matspray); a run folder per method: OUT/run or OUT/run-paper",
    )
    parser.add_argument(
        "--without", nargs="+", choices=ADDITION_NAMES, default=(), help="switch single additions of matspray off"
    )
    parser.add_argument("--light-tv-weight", type=float, help="override the light prior's weight")
    args = parser.parse_args()
    start = time.perf_counter()
    data = make_demo_object(args.out / "data", args.preset, args.shape, args.seed)
    seeds = args.refine_seeds or [args.seed]
    settings = {"refine.iterations": args.refine_iterations, "refine.light_tv_weight": args.light_tv_weight}
    settings = {k: v for k, v in settings.items() if v is not None}
    run_dir = args.out / ("run" if args.method == "matspray" else f"run-{args.method}")
    if run_dir.name != "run":
        share_stage(args.out / "run", run_dir, "geometry")  # geometry does not depend on the method
    runs = [
        run_object(
            data,
            run_dir,
            build_config(
                args.preset, args.method, tuple(args.without), predictor="simulated", refine_seed=seed, **settings
            ),
        )
        for seed in seeds
    ]
    metrics = runs[-1]
    print(f"\nobject: {args.shape} seed {args.seed}, preset {args.preset}, torch threads {torch.get_num_threads()}")
    print(f"held-out lights: {', '.join(metrics['relight_envs'])}")
    print(
        f"refinement seeds: {' '.join(map(str, seeds))}"
        + (" (figures are means over the seeds)" if len(seeds) > 1 else "")
    )
    header = (
        f"{'variant':<16}{'relight PSNR':>13}{'relight SSIM':>13}"
        f"{'basecolor PSNR':>15}{'rough PSNR':>11}{'metal PSNR':>11}"
    )
    print(header + ("   relight PSNR per seed" if len(seeds) > 1 else ""))
    for variant in metrics["variants"]:
        summaries = [run["variants"][variant]["summary"] for run in runs]
        relight, ssim, base, rough, metal = (
            seed_mean(summaries, group, key)
            for group, key in (
                ("relighting", "psnr"),
                ("relighting", "ssim"),
                ("basecolor", "psnr"),
                ("roughness", "psnr"),
                ("metallic", "psnr"),
            )
        )
        per_seed = "   " + " ".join(fmt(s["relighting"]["psnr"]) for s in summaries) if len(seeds) > 1 else ""
        print(
            f"{VARIANT_LABELS[variant]:<16}{fmt(relight):>13}{fmt(ssim, 3):>13}"
            f"{fmt(base):>15}{fmt(rough):>11}{fmt(metal):>11}{per_seed}"
        )
    if "predictions_2d" in metrics:
        p = metrics["predictions_2d"]
        print(
            f"{'2D predictions':<16}{'':>13}{'':>13}"
            f"{fmt(p['basecolor']['psnr']):>15}{fmt(p['roughness']['psnr']):>11}{fmt(p['metallic']['psnr']):>11}"
        )
    timings = RunDir(run_dir).timings()
    print("seconds per stage: " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    print(f"total wall time: {time.perf_counter() - start:.0f} s")
    if args.ceilings:
        print_ceilings(data, args.out, args.preset)


def seed_mean(summaries: list[dict], group: str, key: str):
    """Mean of one figure over the seeds' summaries (None when any seed lacks it; inf stays inf)."""
    values = [s[group].get(key) for s in summaries]
    return None if any(v is None for v in values) else sum(values) / len(values)


def lifted_truth(
    data: Path, out: Path, preset: str, full, views: list, truths: list, lights: dict
) -> tuple[dict, dict]:
    """Summaries of the lifted ground-truth maps on the run's own Gaussians (geometry reused), averaged
    (proj-average) and clamped to the range of the predictor's per-view values (the softmax merger's reach,
    shaded with the `full` asset's normals and shadowing)."""
    from dataclasses import replace

    from matspray.eval.run_eval import evaluate_asset

    run, truth_run = out / "run", out / "run-truth"
    averaged = lift_truth(data, run, truth_run, build_config(preset))
    reach = softmax_reach(averaged.materials, truth_run, run)  # [N, 5]
    return tuple(
        evaluate_asset(asset, views, truths, lights, None)["summary"]
        for asset in (averaged, replace(full, materials=reach.to(full.materials)))
    )


def print_ceilings(data: Path, out: Path, preset: str) -> None:
    from matspray.method.asset import read_asset

    print("\nceilings (what no material estimate can beat here):")
    full = read_asset(out / "run" / "asset")
    views, truths, lights = read_test_truth(data)
    for label, shadows_from in [("unshadowed", None)] + (
        [("our shadowing", full)] if full.visibility is not None else []
    ):
        shading = shading_ceiling(views, truths, lights, shadows_from)
        per_light = ", ".join(f"{name} {fmt(m['psnr'])}" for name, m in shading.items() if name != "relighting")
        print(
            f"shading ceiling ({label}): "
            f"true G-buffer relight PSNR {fmt(shading['relighting']['psnr'])} ({per_light}), "
            f"SSIM {fmt(shading['relighting']['ssim'], 3)}"
        )
    for label, summary in zip(
        ("lifted truth:  ", "softmax merger:"), lifted_truth(data, out, preset, full, views, truths, lights)
    ):
        print(
            f"{label} relight PSNR {fmt(summary['relighting']['psnr'])}, "
            f"basecolor {fmt(summary['basecolor']['psnr'])}, "
            f"roughness {fmt(summary['roughness']['psnr'])}, metallic {fmt(summary['metallic']['psnr'])}"
        )


if __name__ == "__main__":
    main()
