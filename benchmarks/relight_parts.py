"""Where the relighting error of an asset comes from: swap parts of its G-buffer for the truth.

    python -m benchmarks.relight_parts [--out runs/demo-demo] [--variant full] [--data DATA --run RUN]

For every test view and held-out light, the asset's G-buffer (base color, roughness, metallic,
normals, coverage) is shaded as `matspray eval` shades it, then again with one or more parts replaced
by the ground truth of the `matspray synth` object (`test/{view}_{channel}.png`, `{view}_normal.exr`,
the mask). Each row prints the relighting PSNR; the gap to "ours" is what that part costs. The asset's
own shadowing (its baked visibility, from a run with `--set shadows=on`) is kept in every row; the
"shadows off" rows drop it, so that "all true, shadows off" against the shading ceiling is what the baked
shadows are worth to a perfect G-buffer.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.data.images import read_raw
from matspray.eval.evaluate import evaluate_images
from matspray.eval.run_eval import load_relight_lights, read_view_truth, unpremultiply
from matspray.method.asset import read_asset
from matspray.method.relight import render_gbuffer
from matspray.presets import asset_stage
from matspray.render.shade.deferred import GBuffer, shade_gbuffer

MATERIALS = {"base_color", "roughness", "metallic"}
SWAPS = {
    "ours": set(),
    "true base color": {"base_color"},
    "true roughness": {"roughness"},
    "true metallic": {"metallic"},
    "true normals": {"normals"},
    "true materials": MATERIALS,
    "true materials + normals": MATERIALS | {"normals"},
    "all true (shading ceiling)": MATERIALS | {"normals", "alpha"},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--out", type=Path, default=Path("runs/demo-demo"), help="folder with data/ and run/ (a demo's output)"
    )
    parser.add_argument("--variant", default="full")
    parser.add_argument("--data", type=Path, help="the object's folder (default OUT/data)")
    parser.add_argument("--run", type=Path, help="the run folder (default OUT/run), e.g. a benchmark's run")
    args = parser.parse_args()
    data, run = args.data or args.out / "data", args.run or args.out / "run"
    asset = read_asset(run / asset_stage(args.variant))
    scene = load_scene(data)
    truths = [read_view_truth(view) for view in scene.test]
    lights = load_relight_lights(data, sorted(set.intersection(*(set(t.relit) for t in truths))))
    psnr: dict[str, dict[str, list[float]]] = {}
    for view, truth in zip(scene.test, truths):
        true_parts = {
            "base_color": truth.basecolor,
            "roughness": truth.roughness,
            "metallic": truth.metallic,
            "normals": read_raw(view.path.with_name(f"{view.name}_normal.exr"))[..., :3],
            "alpha": truth.mask,
        }
        for env, light in lights.items():
            with torch.no_grad():
                ours = render_gbuffer(asset, view.camera, light)
            rows = {name: (swap, ours.shadow) for name, swap in SWAPS.items()}
            rows["ours, shadows off"] = (set(), None)
            rows["all true, shadows off"] = (MATERIALS | {"normals", "alpha"}, None)
            for name, (swap, shadow) in rows.items():
                parts = {k: (true_parts[k] if k in swap else getattr(ours, k)) for k in true_parts}
                gbuffer = GBuffer(**parts, shadow=shadow)
                with torch.no_grad():
                    rgb = unpremultiply(shade_gbuffer(gbuffer, view.camera, light), gbuffer.alpha)
                value = evaluate_images(rgb, truth.relit[env], truth.mask)["psnr"]
                psnr.setdefault(name, {}).setdefault(env, []).append(value)
    print(f"{args.variant} asset of {run}: relighting PSNR over {len(scene.test)} test views x {len(lights)} lights")
    print(f"{'G-buffer':<30}{'all':>8}" + "".join(f"{env:>10}" for env in lights))
    for name, per_env in psnr.items():
        every = [v for values in per_env.values() for v in values]
        print(
            f"{name:<30}{sum(every) / len(every):>8.2f}"
            + "".join(f"{sum(v) / len(v):>10.2f}" for v in per_env.values())
        )


if __name__ == "__main__":
    main()
