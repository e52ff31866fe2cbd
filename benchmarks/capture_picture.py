"""The README's first picture: a capture's held-out photo, then its asset under the light it estimated, then relit
under other lights, all cut to one square around the object and brought to one size.

    python -m benchmarks.capture_picture --run RUN [--view 09] [--lights studio sunset forest] [--size 256] \
        --out docs/images/skull_relit.png

RUN is a `matspray run` folder of a capture; the asset is the one a command takes when none is named (full, else
photos-only). The view must be one the run never trained on (a test view of its dataset): the picture shows what
the asset makes of a photo it did not see. Columns: the photo as taken; the asset under its estimated light (and
flash, when the photo was taken with one: `refine.camera_light`), over white (as `matspray eval` scores it); the asset
under each light, over that light. The held-out scores that belong beside the picture are the run's `matspray eval`
(`RUN/eval/heldout.json`), kept under docs/results by `benchmarks.real_captures`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from matspray.data import load_run_scene
from matspray.data.images import write_image
from matspray.eval.capture_report import RELIGHT_ENV_HEIGHT
from matspray.eval.heldout import estimated_lights
from matspray.eval.relit_crops import crop, default_asset, square_box
from matspray.method.refine.camera_light import lighting
from matspray.method.relight import background_radiance, render_relit
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import load_envmap
from matspray.rundir import RunDir

WHITE = 1.0  # linear background of the column under the estimated light, as the held-out scores composite it


def picture(run: RunDir, view_name: str | None, lights: list[str], size: int) -> tuple[torch.Tensor, str, list[str]]:
    """The row [size, size * (2 + len(lights)), 3] linear, the view's name and the columns' labels."""
    test = load_run_scene(run).test
    if not test:
        raise SystemExit(f"{run.root}: its dataset has no held-out (test) views to show")
    view = test[0] if view_name is None else next((v for v in test if v.name == view_name), None)
    if view is None:
        raise SystemExit(f"no held-out view {view_name} in {run.root}: {', '.join(v.name for v in test)}")
    variant = run.default_variant()
    asset = default_asset(run)
    estimated = estimated_lights(run, [variant], "cpu").get(variant)
    if estimated is None:
        raise SystemExit(f"{run.root}: the {variant} asset has no estimated light (envmap.exr) to show it under")
    with torch.no_grad():
        flash = lighting(asset.camera_light, view.path)  # as the held-out scores render it
        rgb, alpha = render_relit(asset, view.camera, estimated, camera_light=flash)
        label = "its estimated light" if flash is None else "its estimated light and flash"
        columns, labels = [view.image.cpu(), rgb + WHITE * (1 - alpha[..., None])], ["photo", label]
        for spec in lights:
            name, env = load_envmap(spec, height=RELIGHT_ENV_HEIGHT)
            light = EnvironmentMap.from_tensor(env, learnable=False)
            lit, lit_alpha = render_relit(asset, view.camera, light.prefilter())
            columns.append(lit + background_radiance(light, view.camera) * (1 - lit_alpha[..., None]))
            labels.append(name)
    box = square_box([alpha])
    if box is None:
        raise SystemExit(f"the asset covers no pixel of view {view.name}")
    return torch.cat([crop(column.clamp_min(0), box, size) for column in columns], dim=1), view.name, labels


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--view", help="a held-out view of the run's dataset (default: the first)")
    parser.add_argument("--lights", nargs="+", default=["studio", "sunset", "forest"])
    parser.add_argument("--size", type=int, default=256, help="side of each column in pixels")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    row, view, labels = picture(RunDir(args.run).require(), args.view, args.lights, args.size)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_image(args.out, row)
    print(f"wrote {args.out}: held-out view {view}; columns: {', '.join(labels)}")


if __name__ == "__main__":
    main()
