"""Object focus in Gaussian Splatting of a capture without masks: once the object region is found, only the
object's Gaussians grow and the background keeps a budget (matspray.geometry.densify, geometry.train)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from matspray.data.scene import Scene, View
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.geometry import densify
from matspray.geometry.config import FOCUS, GeometryConfig, preset
from matspray.geometry.densify import DensityControl, load_stats_state, stats_state
from matspray.geometry.optim import GaussianOptimizer
from matspray.geometry.region import ObjectRegion, given_region
from matspray.geometry.train import focus_step, load_checkpoint, save_checkpoint, train_geometry
from matspray.method.masks import read_region
from matspray.render.raster.rasterize import rasterize
from tests.test_geometry import one_thread  # noqa: F401  (fixture: one torch thread)
from tests.test_geometry_parts import LRS, gaussians_from
from tests.test_object_masks import orbit

BALL = ObjectRegion(center=(0.0, 0.0, 0.0), radius=1.0)


def test_focus_step_is_the_first_densification_at_or_after_its_fraction():
    assert focus_step(preset("demo")) == 500  # 0.15 x 3000 = 450 -> the densification at 500
    assert focus_step(preset("paper")) == 3000  # 0.1 x 30000, itself a densification step
    assert focus_step(preset("test")) == 30  # 9 is before densify_from (20): the first densification after it
    assert focus_step(preset("demo", focus_from=0.0)) is None
    assert focus_step(preset("demo", focus_from=0.7)) is None  # 2100: densification has ended (2000)
    with pytest.raises(SettingError, match="focus_from"):
        preset("demo", focus_from=1.5)
    with pytest.raises(SettingError, match="focus_grad_scale"):
        preset("demo", focus_grad_scale=0.0)


def test_a_scene_with_masks_keeps_the_fingerprint_it_had_before_the_focus():
    config = preset("demo")
    masked = config.for_scene(masked=True)
    assert not set(FOCUS) & set(masked.identity())  # as before these settings existed
    assert set(FOCUS) <= set(config.for_scene(masked=False).identity())
    assert masked.identity() == preset("demo", focus_grad_scale=0.9, background_budget=0.5).for_scene(True).identity()
    assert focus_step(masked) is None


def test_focus_prunes_the_background_to_its_budget_keeping_what_covers_most(monkeypatch):
    monkeypatch.setattr(densify, "MIN_FOCUS_GAUSSIANS", 1)  # six Gaussians in all here
    config = replace(preset("test"), max_gaussians=10, background_budget=0.2)  # the background keeps 2
    means = [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]] + [[3.0 + i, 0.0, 0.0] for i in range(4)]
    scales = [[0.01] * 3, [0.01] * 3, [0.1] * 3, [0.3] * 3, [0.3, 0.3, 0.001], [0.2] * 3]
    opacities = [0.9, 0.01, 0.9, 0.5, 0.9, 0.1]  # cover (opacity x two larger axes): 9e-3, 4.5e-2, 8.1e-2, 4e-3
    optimizer = GaussianOptimizer(gaussians_from(means, scales, opacities), LRS)
    control = DensityControl(config, extent=1.0, num_gaussians=6)
    message = control.focus(optimizer, BALL)
    kept = optimizer.params["means"].detach()[:, 0].tolist()
    assert kept == [0.0, 0.5, 4.0, 5.0]  # both of the object (even the faint one); the two largest covers outside
    assert "2 Gaussians in the sphere" in message and "4 outside, 2 of those pruned" in message
    assert control.region == BALL and len(control.grad_sum) == 4


def test_a_region_with_almost_no_gaussians_is_not_focused_on():
    g = gaussians_from([[0.0, 0.0, 0.0]] + [[3.0 + i, 0.0, 0.0] for i in range(99)], [[0.01] * 3] * 100, [0.5] * 100)
    optimizer = GaussianOptimizer(g, LRS)
    control = DensityControl(preset("test"), extent=1.0, num_gaussians=100)
    message = control.focus(optimizer, BALL)  # 1 of 100 inside: under the 10 an object needs
    assert message.startswith("object focus skipped: the sphere") and "holds 1 of 100 Gaussians" in message
    assert control.region is None and len(optimizer.params["means"]) == 100


def test_after_the_focus_only_the_object_grows_at_its_own_threshold():
    config = replace(preset("test"), grad_threshold=1e-3, focus_grad_scale=0.5, max_gaussians=100)
    g = gaussians_from([[0, 0, 0], [0.2, 0, 0], [5, 0, 0], [6, 0, 0]], [[0.005] * 3] * 4, [0.5] * 4)
    grads = torch.tensor([6e-4, 4e-4, 2e-3, 6e-4])  # #0 passes the object's threshold (5e-4) only, #2 both

    def densified(region):
        optimizer = GaussianOptimizer(g, LRS)
        control = DensityControl(config, extent=1.0, num_gaussians=4)
        control.region, control.grad_sum, control.count = region, grads.clone(), torch.ones(4)
        control.densify_and_prune(optimizer, torch.Generator().manual_seed(0), prune_large=False)
        return optimizer.params["means"].detach()[4:, 0].tolist()  # the clones

    assert densified(None) == [5.0]  # without focus: the background's strong gradient
    assert densified(BALL) == [0.0]  # focused: the object's Gaussian at half the threshold, no background


def test_the_focus_region_survives_a_checkpoint(tmp_path):
    config = preset("test")
    control = DensityControl(config, extent=1.0, num_gaussians=3)
    control.region = ObjectRegion(center=(0.1, 0.2, 0.3), radius=0.7, plane=(0.0, 0.0, 1.0, 0.5), rule="auto")
    save_checkpoint(tmp_path / "c.pt", config, 40, {"density": stats_state(control)})
    _, state = load_checkpoint(tmp_path / "c.pt", config)
    resumed = DensityControl(config, extent=1.0, num_gaussians=0)
    load_stats_state(resumed, state["density"])
    assert resumed.region == control.region and len(resumed.count) == 3
    load_stats_state(resumed, {**state["density"], "region": None})
    assert resumed.region is None


# ------------------------------------------------------------------------------------------ training
def room_with_a_ball(views: int = 10, size: int = 40) -> Scene:
    """Photos without masks, rendered from Gaussians: a speckled ball (radius 0.5) on a checkered table and a
    striped wall behind, so that the room has detail to spend Gaussians on as well as the object."""
    g = torch.Generator().manual_seed(3)
    ball = torch.nn.functional.normalize(torch.randn(800, 3, generator=g), dim=-1) * 0.5
    u, v = (torch.rand(2, 3000, generator=g) * 2 - 1) * 3.0
    table = torch.stack([u, v, torch.full_like(u, -0.5)], -1)
    table = table[table[:, :2].norm(dim=-1) > 0.45]
    a, b = (torch.rand(2, 2000, generator=g) * 2 - 1) * 3.0
    wall = torch.stack([torch.full_like(a, -3.0), a, b], -1)
    means = torch.cat([ball, table, wall])
    colour = torch.cat(
        [
            torch.rand(len(ball), 3, generator=g),
            ((torch.floor(table[:, :1] * 2) + torch.floor(table[:, 1:2] * 2)) % 2).repeat(1, 3) * 0.8 + 0.1,
            ((torch.floor(wall[:, 1:2] * 3) % 2) * torch.tensor([[0.8, 0.3, 0.2]])) + 0.1,
        ]
    )
    quats = torch.zeros(len(means), 4)
    quats[:, 0] = 1
    truth = Gaussians(
        means, torch.full((len(means), 3), math.log(0.06)), quats, torch.full((len(means),), 4.0), colour[:, None, :]
    )
    cameras = [c for c in orbit(views, distance=2.5, elevation_deg=30.0, size=size)]
    photos = [
        View(f"v{i:02d}", rasterize(truth, c, colour).features.clamp(0, 1).detach(), None, c)
        for i, c in enumerate(cameras)
    ]
    return Scene(train=photos[:-2], test=photos[-2:], bounds=torch.tensor([[-1.5] * 3, [1.5] * 3]))


def test_focus_spends_the_budget_on_the_object(tmp_path):
    scene = room_with_a_ball()
    base = GeometryConfig(
        preset="test",
        resolution=0,
        iterations=160,
        init_points=600,
        sh_degree=0,
        densify_from=20,
        densify_until=150,
        densify_every=20,
        opacity_reset_every=1000,
        max_gaussians=1500,
        checkpoint_every=1000,
        normal_weight=0.0,
        focus_from=0.25,
        focus_grad_scale=0.5,
        background_budget=0.2,
    )
    ball = ObjectRegion(center=(0.0, 0.0, 0.0), radius=0.6, plane=(0.0, 0.0, 1.0, 0.45))

    def on_the_ball(config, name):
        gaussians = train_geometry(scene, config, tmp_path / name, progress=False, object_bounds=(0, 0, 0, 0.8))
        return int(ball.contains(gaussians.means.detach()).sum()), len(gaussians)

    focused, total = on_the_ball(base, "focused")
    before, total_before = on_the_ball(replace(base, focus_from=0.0), "unfocused")
    assert focused >= 1.5 * before, (focused, before)
    assert read_region(tmp_path / "focused") == given_region((0, 0, 0, 0.8))  # for the masks stage
    assert not (tmp_path / "unfocused" / "region.json").exists()
    assert focused / total >= 4 * before / total_before, (
        focused,
        total,
        before,
        total_before,
    )  # measured 551 / 1300, 66 / 1487
