"""Evaluation figures computed again in the tests, with numpy, from the asset's renders and the dataset's truth: the
reference that `matspray eval`'s numbers are checked against (tests/test_pipeline.py, test_no_prior.py,
test_batch.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def srgb(linear: np.ndarray) -> np.ndarray:  # the sRGB transfer function (IEC 61966-2-1), of values clamped to [0, 1]
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 1e-12) ** (1.0 / 2.4) - 0.055)


def relighting_psnr(run: Path, data: Path, variant: str = "full", backend: str = "torch") -> float:
    """The object-mask relighting PSNR of `variant`'s asset: its renders under each held-out light of `data`
    (MatSpray's renderer, `backend`) and the relit truth, both composited over white with the true mask and
    sRGB-encoded, -10 log10 of their mean squared error, averaged over the test views and the lights."""
    from matspray.data import load_scene
    from matspray.eval.run_eval import asset_renders, load_relight_lights, read_view_truth
    from matspray.method.asset import read_asset
    from matspray.render.backend import rendering_with
    from matspray.rundir import RunDir

    run_dir = RunDir(run)
    scene = load_scene(data, downscale=run_dir.downscale())
    truths = [read_view_truth(view) for view in scene.test]
    envs = sorted(set.intersection(*(set(truth.relit) for truth in truths)))
    assert envs, f"{data}: no relit ground truth"
    lights = load_relight_lights(Path(data), envs)
    asset = read_asset(run_dir.asset_path(variant))
    values = []
    with rendering_with(backend):
        for view, truth in zip(scene.test, truths):
            relit = asset_renders(asset, view, lights).relit
            mask = truth.mask.double().numpy()[..., None]
            for env in envs:
                pred = srgb(relit[env].double().numpy() * mask + (1.0 - mask))
                target = srgb(truth.relit[env].double().numpy() * mask + (1.0 - mask))
                values.append(-10.0 * np.log10(np.mean((pred - target) ** 2)))
    return float(np.mean(values))
