"""Relit crops of the object, run beside run: one camera, one light, the asset of each of several runs of the same
capture, all cut to the same square around the object and brought to the same size, beside the photo.

What shows whether a change of settings gave the object more detail (the "before/after": the object focus, a
larger budget, another working size). The runs are rendered with the first run's camera: every run of one capture
lives in the same world, so runs made at different working sizes are compared at one."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.images import read_image, resize
from matspray.data.scene import View
from matspray.errors import DataError
from matspray.eval.run_eval import relight_env_names, relight_light
from matspray.method.asset import Asset, read_asset
from matspray.method.relight import render_relit
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir

GREY = 0.5  # linear background of the crops: neither the photo's backdrop nor a light
MARGIN = 0.08  # of the crop's side, around the object


def default_asset(run: RunDir, device="cpu") -> Asset:
    """The asset a command takes when none is named (`RunDir.default_variant`)."""
    return read_asset(run.asset_path(run.default_variant()), device=device)


def same_capture(runs: list[RunDir]) -> None:
    """DataError unless every run was made from the first run's dataset folder."""
    source = Path(runs[0].dataset()["source"]).resolve()
    for run in runs[1:]:
        other = Path(run.dataset()["source"]).resolve()
        if other != source:
            raise DataError(
                f"{run.root} was made from {other}, not {source} (the data of {runs[0].root}): "
                "compare runs of the same capture"
            )


def square_box(alphas: list[Tensor]) -> tuple[int, int, int] | None:  # alphas: [H, W] each
    """(top, left, side) of the square around every alpha's object pixels (alpha >= 0.5), with a margin, inside the
    image; None when no alpha covers any pixel."""
    covered = torch.stack([a >= 0.5 for a in alphas]).any(dim=0)
    rows, cols = torch.nonzero(covered, as_tuple=True)
    if len(rows) == 0:
        return None
    height, width = covered.shape
    extent = max(int(rows.max() - rows.min()), int(cols.max() - cols.min()))
    side = min(int(extent * (1 + 2 * MARGIN)) + 1, height, width)
    top = min(max((int(rows.min()) + int(rows.max()) - side) // 2, 0), height - side)
    left = min(max((int(cols.min()) + int(cols.max()) - side) // 2, 0), width - side)
    return top, left, side


def relit_truth(view: View, env: str, data: Path) -> tuple[Tensor, EnvironmentMap] | None:
    """A synthetic object's truth for `view` relit under its held-out light `env` (`test/VIEW_relight_ENV.png`, over
    GREY by its alpha, linear) and that light as `matspray eval` relights with it (`run_eval.relight_light`); None
    where the view has no such truth (a capture: its photo is the reference). data: the dataset folder."""
    if env not in relight_env_names(view):
        return None
    rgb, alpha = read_image(view.path.with_name(f"{view.name}_relight_{env}.png"))
    if alpha is not None:
        rgb = rgb * alpha[..., None] + GREY * (1 - alpha[..., None])
    return rgb, relight_light(data, env)


def crop(image: Tensor, box: tuple[int, int, int], size: int) -> Tensor:  # [H, W, C] -> [size, size, C]
    top, left, side = box
    return resize(image[top : top + side, left : left + side].contiguous(), size, size)


def relit_crops(
    assets: list[Asset], camera: Camera, light, photo: Tensor | None = None, size: int = 256
) -> Tensor | None:  # -> [size, size * columns, 3] linear
    """The photo (when given, [H, W, 3] linear at the camera's size) then each asset relit under `light` (prefiltered)
    over grey, cut to the square around the assets' object pixels, side by side; None when no asset covers a pixel."""
    columns, alphas = [], []
    with torch.no_grad():
        for asset in assets:
            rgb, alpha = render_relit(asset, camera, light)
            columns.append((rgb + GREY * (1 - alpha[..., None])).cpu())
            alphas.append(alpha.cpu())
    box = square_box(alphas)
    if box is None:
        return None
    if photo is not None:
        columns.insert(0, photo.cpu())
    return torch.cat([crop(c, box, size) for c in columns], dim=1)
