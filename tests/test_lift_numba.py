"""Lifting's compiled ray tracing (matspray.render.numba.rays) against the torch tracer's entries, and the lift it
gives against the torch lift."""

from __future__ import annotations

import math

import pytest
import torch

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.method.lift import LiftConfig, compiled_entries, footprint_alpha, lift, traced_entries
from matspray.render.backend import rendering_with
from matspray.render.numba.rays import tile_row_bands
from matspray.render.settings import RasterSettings
from tests.test_contributions import scene_with_awkward_gaussians

SETTINGS = RasterSettings()


def dense_scene(seed: int, n: int = 400, width: int = 37, height: int = 29) -> tuple[Gaussians, Camera]:
    """Many overlapping Gaussians, some nearly opaque (rays stop early), some faint, over several 16 px tiles (the
    image's sides are no multiples of 16)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.4
    log_scales = torch.log(0.02 + 0.15 * torch.rand(n, 3, generator=g))
    opacity = torch.where(torch.rand(n, generator=g) < 0.3, 0.999, 0.01 + 0.9 * torch.rand(n, generator=g))
    gaussians = Gaussians(means, log_scales, torch.randn(n, 4, generator=g), torch.logit(opacity), torch.zeros(n, 1, 3))
    camera = Camera.look_at([0.4, -3.5, 0.9], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), width, height)
    return gaussians, camera


def sorted_entries(keys: torch.Tensor, counts: torch.Tensor) -> tuple[list[int], list[int]]:
    order = torch.argsort(keys)
    return keys[order].tolist(), counts[order].tolist()


def both_entries(gaussians, camera, mask, config):
    core = footprint_alpha(gaussians.opacities.detach(), config, SETTINGS.max_alpha)
    return (
        sorted_entries(*traced_entries(gaussians, camera, mask, config, SETTINGS, core)),
        sorted_entries(*compiled_entries(gaussians, camera, mask, config, SETTINGS, core)),
    )


@pytest.mark.parametrize(
    "seed,config",
    [
        (0, LiftConfig(samples_per_side=1)),
        (1, LiftConfig(samples_per_side=3)),
        (2, LiftConfig(samples_per_side=4, footprint_sigmas=None)),
        (3, LiftConfig(samples_per_side=2, visibility_threshold=0.5, footprint_sigmas=1.5, falloff=2.0)),
    ],
)
def test_the_compiled_tracer_gives_the_torch_tracers_entries(seed, config):
    gaussians, camera = dense_scene(seed)
    mask = (torch.rand(camera.height, camera.width, generator=torch.Generator().manual_seed(seed)) > 0.3).float()
    for view_mask in (None, mask):
        expected, got = both_entries(gaussians, camera, view_mask, config)
        assert len(expected[0]) > 500  # a scene with many entries
        assert got == expected


def test_gaussians_around_and_behind_the_camera_are_traced_as_by_torch():
    for seed in range(3):
        gaussians, camera = scene_with_awkward_gaussians(seed)
        expected, got = both_entries(gaussians, camera, None, LiftConfig(samples_per_side=2))
        assert got == expected and len(expected[0]) > 0


def test_a_band_budget_smaller_than_the_image_gives_the_same_entries(monkeypatch):
    from matspray.render.numba import rays as numba_rays

    gaussians, camera = dense_scene(5, width=40, height=70)
    config = LiftConfig(samples_per_side=2)
    whole = both_entries(gaussians, camera, None, config)[1]
    bands = []
    monkeypatch.setattr(numba_rays, "MAX_BAND_ENTRIES", 1)  # one tile row per band
    monkeypatch.setattr(numba_rays, "tile_row_bands", lambda *a: bands.extend(tile_row_bands(*a)) or bands)
    assert both_entries(gaussians, camera, None, config)[1] == whole
    assert bands == [(row, row + 1) for row in range(5)]


def test_bands_hold_whole_tile_rows_within_the_budget():
    candidates = torch.zeros(40 * 50, dtype=torch.long).numpy()
    candidates[: 16 * 40] = 3  # first tile row: 2 * 3 * 640 entries
    candidates[16 * 40 :] = 1
    assert tile_row_bands(candidates, 40, 50, budget=10**9) == [(0, 4)]
    assert tile_row_bands(candidates, 40, 50, budget=2600) == [(0, 1), (1, 3), (3, 4)]  # 3840, 2 x 1280, 160
    assert tile_row_bands(candidates, 40, 50, budget=1) == [(0, 1), (1, 2), (2, 3), (3, 4)]


def test_lifting_with_backend_numba_gives_the_torch_lift():
    gaussians, camera = dense_scene(7)
    cameras = [
        camera,
        Camera.look_at([-2.5, -2.5, 1.5], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(40), 33, 30),
    ]
    g = torch.Generator().manual_seed(7)
    maps = [torch.rand(c.height, c.width, 5, generator=g) for c in cameras]
    masks = [None, (torch.rand(30, 33, generator=g) > 0.2).float()]
    lifted = {}
    for backend in ("torch", "numba"):
        with rendering_with(backend) as use:
            lifted[backend] = lift(gaussians, cameras, maps, masks, ["a", "b"], LiftConfig(samples_per_side=3), False)
        assert use.used() == {"rays-numba" if backend == "numba" else "rays": 2}
    torch_lift, numba_lift = lifted["torch"], lifted["numba"]
    assert torch_lift.kept.sum() > 100
    for name in ("values", "seen", "kept", "hits"):
        assert torch.equal(getattr(numba_lift, name), getattr(torch_lift, name)), name


@pytest.mark.parametrize("seed", [0, 1])
def test_the_torch_tracers_entries_do_not_depend_on_its_band_size(monkeypatch, seed):
    # on a GPU the tracer takes bands as large as its memory allows (lift.band_samples): whole rays either way, so
    # the same entries as in the CPU's small bands, here from one band for the whole view down to bands of a row
    import matspray.method.lift as lift_module

    assert lift_module.band_samples(torch.device("cpu")) == lift_module.DEFAULT_BAND_SAMPLES
    gaussians, camera = dense_scene(seed)
    config = LiftConfig(samples_per_side=3)
    core = footprint_alpha(gaussians.opacities.detach(), config, SETTINGS.max_alpha)
    traced = lift_module.iter_contributions
    bands = []

    def counted(*args, **kwargs):
        for band in traced(*args, **kwargs):
            bands[-1] += 1
            yield band

    monkeypatch.setattr(lift_module, "iter_contributions", counted)
    results = []
    for samples in (1 << 30, 1 << 16, 9):
        monkeypatch.setattr(lift_module, "band_samples", lambda device, samples=samples: samples)
        bands.append(0)
        results.append(sorted_entries(*traced_entries(gaussians, camera, None, config, SETTINGS, core)))
    assert results[0] == results[1] == results[2]
    assert bands[0] == 1 < bands[1] < bands[2] == camera.height
