"""Pieces of geometry training: density control, the optimizer's row edits, normals, losses, init."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from matspray.data.camera import Camera
from matspray.data.scene import Scene, View
from matspray.errors import SettingError
from matspray.gaussians import Gaussians
from matspray.geometry.config import preset
from matspray.geometry.densify import DensityControl, split_gaussians
from matspray.geometry.init import hull_surface_points, initial_gaussians, neighbour_spacing
from matspray.geometry.losses import flatten_loss, normal_consistency_loss
from matspray.geometry.normals import consensus_normals, depth_normals, oriented_normals, render_normals
from matspray.geometry.optim import GaussianOptimizer, exponential_lr
from matspray.metrics import ssim_loss
from tests.test_geometry import one_thread  # noqa: F401  (fixture: one torch thread)

LRS = {"means": 0.01, "log_scales": 0.01, "quats": 0.01, "opacity_logits": 0.01, "sh_dc": 0.01, "sh_rest": 0.01}


def gaussians_from(means, scales, opacities):
    n = len(means)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return Gaussians(
        torch.tensor(means, dtype=torch.float32),
        torch.log(torch.tensor(scales, dtype=torch.float32)),
        quats,
        torch.logit(torch.tensor(opacities)),
        torch.zeros(n, 4, 3),
    )


def test_density_control_clones_splits_and_prunes():
    config = replace(preset("test"), grad_threshold=1e-3, percent_dense=0.01, prune_opacity=0.005, max_gaussians=100)
    g = gaussians_from(
        [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]],
        [[0.005] * 3, [0.5, 0.2, 0.1], [0.005] * 3, [0.005] * 3],
        [0.5, 0.5, 0.5, 0.001],
    )
    optimizer = GaussianOptimizer(g, LRS)
    # one Adam step so that the moments are non-zero, then check they follow their rows
    sum(t.sum() for t in optimizer.params.values()).backward()
    optimizer.step()
    moments_before = optimizer.adam.state[optimizer.params["means"]]["exp_avg"].clone()
    means_before = optimizer.params["means"].detach().clone()  # after the Adam step
    scales_before = optimizer.params["log_scales"].detach().exp().clone()
    control = DensityControl(config, extent=1.0, num_gaussians=4)
    control.grad_sum = torch.tensor([2e-3, 2e-3, 1e-4, 0.0])  # #0 small and #1 large have big gradients
    control.count = torch.ones(4)
    message = control.densify_and_prune(optimizer, torch.Generator().manual_seed(0), prune_large=False)
    means = optimizer.params["means"].detach()
    # kept: #0 and #2 (#1 split away, #3 transparent), then the clone of #0 and two children of #1
    assert len(means) == 5 and "+1 cloned" in message and "+2 split from 1" in message and "-1 pruned" in message
    torch.testing.assert_close(means[:3], means_before[[0, 2, 0]])
    children_scales = optimizer.params["log_scales"].detach()[3:].exp()
    torch.testing.assert_close(children_scales, scales_before[[1, 1]] / 1.6)
    moments = optimizer.adam.state[optimizer.params["means"]]["exp_avg"]
    torch.testing.assert_close(moments[:2], moments_before[[0, 2]])
    assert (moments[2:] == 0).all()
    assert control.grad_sum.shape == (5,) and (control.grad_sum == 0).all()


def test_density_control_respects_the_cap():
    config = replace(preset("test"), grad_threshold=1e-3, max_gaussians=5)
    g = gaussians_from([[i, 0, 0] for i in range(4)], [[0.005] * 3] * 4, [0.5] * 4)
    optimizer = GaussianOptimizer(g, LRS)
    control = DensityControl(config, extent=1.0, num_gaussians=4)
    control.grad_sum, control.count = torch.tensor([2e-3, 5e-3, 3e-3, 4e-3]), torch.ones(4)
    control.densify_and_prune(optimizer, torch.Generator().manual_seed(0), prune_large=False)
    means = optimizer.params["means"].detach()
    assert len(means) == 5 and means[4, 0] == 1  # only the strongest gradient was cloned


def test_split_children_are_samples_of_the_parent():
    parent = gaussians_from([[0.0, 0.0, 0.0]], [[1.0, 0.1, 0.01]], [0.5]).subset(torch.zeros(2000, dtype=torch.long))
    children = split_gaussians(parent, torch.Generator().manual_seed(0))
    spread = children.means.std(dim=0)
    torch.testing.assert_close(spread, torch.tensor([1.0, 0.1, 0.01]), rtol=0.08, atol=0)


def test_optimizer_learning_rate_schedule():
    assert math.isclose(exponential_lr(0, 100, 1e-2, 1e-4), 1e-2)
    assert math.isclose(exponential_lr(50, 100, 1e-2, 1e-4), 1e-3)
    assert math.isclose(exponential_lr(100, 100, 1e-2, 1e-4), 1e-4)


def test_depth_normals_of_a_plane():
    camera = Camera.look_at([0.0, -3.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], math.radians(50), 24, 20)
    # the plane z = -0.5: its camera z along each pixel's ray
    origins, dirs = camera.rays()
    t = (-0.5 - origins[:, 2]) / dirs[:, 2]
    z_cam = (t[:, None] * dirs) @ camera.viewmat[:3, :3].T[:, 2:]  # camera z of the hit
    normals = depth_normals(z_cam.reshape(20, 24), camera)
    interior = normals[1:-1, 1:-1].reshape(-1, 3)
    torch.testing.assert_close(interior, torch.tensor([[0.0, 0.0, 1.0]]).expand_as(interior), atol=1e-4, rtol=0)
    assert (normals[0] == 0).all()


def test_normals_face_the_camera_and_agree_across_views():
    """Flat Gaussians tiling a sphere: per view they face the camera; the consensus points outwards."""
    n = 300
    golden = math.pi * (3 - math.sqrt(5))
    i = torch.arange(n, dtype=torch.float32)
    z = 1 - 2 * (i + 0.5) / n
    r = torch.sqrt(1 - z * z)
    outward = torch.stack([r * torch.cos(golden * i), r * torch.sin(golden * i), z], -1)
    half = torch.nn.functional.normalize(outward + torch.tensor([0.0, 0.0, 1.0]), dim=-1)  # rotates +z onto the normal
    quats = torch.cat(
        [
            half[:, 2:3],  # w = z . h, xyz = z x h: the rotation taking +z to the normal
            torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), half),
        ],
        -1,
    )
    quats[outward[:, 2] < -0.999] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    g = Gaussians(
        outward,
        torch.log(torch.tensor([[0.12, 0.12, 0.005]])).repeat(n, 1),
        quats,
        torch.logit(torch.full((n,), 0.9)),
        torch.zeros(n, 1, 3),
    )
    cameras = [
        Camera.look_at([4 * math.cos(a), 4 * math.sin(a), 1.0], [0, 0, 0], [0, 0, 1], math.radians(40), 32, 32)
        for a in (0.0, 2.1, 4.2)
    ]
    torch.testing.assert_close(g.normals().abs(), outward.abs(), atol=1e-5, rtol=0)
    facing = oriented_normals(g, cameras[0])
    assert ((facing * (cameras[0].center - g.means)).sum(-1) >= 0).all()
    consensus = consensus_normals(g, cameras)
    seen = (outward @ torch.stack([c.center for c in cameras]).T > 1.2).any(dim=1)  # n . c > |mu| = 1: front side
    agree = (consensus[seen] * outward[seen]).sum(-1) > 0.999
    assert agree.float().mean() > 0.99  # a few grazing discs also show through gaps from behind
    normal_map, alpha = render_normals(g, cameras[1])
    centre = normal_map[16, 16]
    torch.testing.assert_close(centre, torch.nn.functional.normalize(cameras[1].center, dim=0), atol=0.05, rtol=0)
    assert alpha[16, 16] > 0.9


def test_losses():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(24, 20, 3, generator=g)
    assert abs(1 - float(ssim_loss(image, image)) - 1) < 1e-6
    noisy = (image + 0.1 * torch.randn(24, 20, 3, generator=g)).clamp(0, 1)
    assert 1 - float(ssim_loss(image, noisy)) < 1 - float(ssim_loss(image, (image + noisy) / 2)) < 1
    assert math.isclose(
        float(flatten_loss(torch.log(torch.tensor([[1.0, 0.1, 0.5], [2.0, 2.0, 2.0]])))), (0.2 + 1) / 2, rel_tol=1e-6
    )
    n = torch.nn.functional.normalize(torch.randn(5, 6, 3, generator=g), dim=-1)
    weights = torch.ones(5, 6)
    assert float(normal_consistency_loss(3 * n, n, weights)) < 1e-6
    assert math.isclose(float(normal_consistency_loss(-n, n, weights)), 2.0, rel_tol=1e-6)


def test_initial_points_lie_on_the_visual_hull():
    """A ball of radius 0.5 seen by 6 masked views: the hull points lie on (slightly inside) its surface."""
    cameras = [
        Camera.look_at(list(v), [0, 0, 0], [0, 0, 1] if abs(v[2]) < 1 else [0, 1, 0], math.radians(40), 40, 40)
        for v in ([3, 0, 0], [-3, 0, 0], [0, 3, 0], [0, -3, 0], [0, 0, 3], [0, 0, -3])
    ]
    views = []
    for camera in cameras:
        origins, dirs = camera.rays()
        b = (origins * dirs).sum(-1)
        hit = (b * b - (origins.square().sum(-1) - 0.25)) > 0
        views.append(View(f"v{len(views)}", torch.full((40, 40, 3), 0.5), hit.float().reshape(40, 40), camera))
    bounds = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    points, colours = hull_surface_points(bounds, views, 600, torch.Generator().manual_seed(0))
    radius = points.norm(dim=-1)
    assert len(points) >= 500 and radius.max() < 0.62 and radius.min() > 0.45  # the 6-view hull bulges past the ball
    torch.testing.assert_close(colours, torch.full_like(colours, float(colours[0, 0])))
    scene = Scene(train=views, test=[], bounds=bounds)
    g = initial_gaussians(scene, views, 600, 2, 0.3, torch.Generator().manual_seed(0), scale=0.5)
    assert g.sh.shape[1:] == (9, 3) and (g.sh[:, 1:] == 0).all()
    torch.testing.assert_close(g.opacities, torch.full((len(g),), 0.3))
    torch.testing.assert_close(g.scales[:, 0], 0.5 * neighbour_spacing(g.means))


def test_the_papers_start_fills_the_masked_objects_box_uniformly(monkeypatch):
    """`init="random"` (the paper's 100 000 points in a unit cube, l.209): a masked object's Gaussians start anywhere in
    its bounds, not on its hull, and geometry training passes the setting to the start."""
    from matspray.geometry import train as train_module
    from matspray.geometry.config import GeometryConfig

    cameras = [Camera.look_at([3 * math.cos(a), 3 * math.sin(a), 1], [0, 0, 0], [0, 0, 1], 0.8, 24, 24) for a in (0, 2)]
    disc = torch.zeros(24, 24)
    disc[8:16, 8:16] = 1.0
    views = [View(f"v{i}", torch.full((24, 24, 3), 0.5), disc, c) for i, c in enumerate(cameras)]
    bounds = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    scene = Scene(train=views, test=[], bounds=bounds)
    g = initial_gaussians(scene, views, 4000, 0, 0.3, torch.Generator().manual_seed(0), start="random")
    assert len(g) == 4000 and bool((g.means.abs() <= 1.0).all())
    # uniform in the box: each octant holds about an eighth, and the mean is near the centre
    octants = torch.bincount(((g.means > 0).long() * torch.tensor([1, 2, 4])).sum(-1), minlength=8)
    assert int(octants.min()) > 400 and float(g.means.mean(0).abs().max()) < 0.05
    hull = initial_gaussians(scene, views, 4000, 0, 0.3, torch.Generator().manual_seed(0))
    assert float(hull.means.norm(dim=-1).max()) < 0.9 * float(g.means.norm(dim=-1).max())  # the hull is inside
    with pytest.raises(SettingError, match="^init: unknown start 'cube'; choose one of hull, random"):
        GeometryConfig(init="cube")
    seen = []
    monkeypatch.setattr(train_module, "initial_gaussians", lambda *a, **k: seen.append(a[-1]) or g)
    train_module.training_state(scene, views, GeometryConfig(init="random"), 1.0, None, None, torch.device("cpu"))
    assert seen == ["random"]


def test_a_few_points_of_a_capture_without_masks_are_topped_up_with_scattered_ones():
    cameras = [Camera.look_at([3 * math.cos(a), 3 * math.sin(a), 1], [0, 0, 0], [0, 0, 1], 0.8, 24, 24) for a in (0, 2)]
    views = [View(f"v{i}", torch.full((24, 24, 3), 0.5), None, c) for i, c in enumerate(cameras)]
    bounds = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    sparse = torch.rand(150, 3, generator=torch.Generator().manual_seed(1)) * 0.5  # 15 % of the count
    scene = Scene(train=views, test=[], bounds=bounds, points=sparse)
    g = initial_gaussians(scene, views, 1000, 0, 0.3, torch.Generator().manual_seed(0))
    assert len(g) == 1000
    torch.testing.assert_close(g.means[:150], sparse)  # the points first, then the scattered rest
    in_bounds = (g.means[150:].abs() <= 1.0).all(-1)
    assert int(in_bounds.sum()) == 850 - int(0.25 * 850)  # the rest in the bounds, a quarter on the far shell
    enough = Scene(train=views, test=[], bounds=bounds, points=torch.rand(300, 3) * 0.5)  # 30 %: used alone
    assert len(initial_gaussians(enough, views, 1000, 0, 0.3, torch.Generator().manual_seed(0))) == 300
    masked = [View(v.name, v.image, torch.ones(24, 24), v.camera) for v in views]
    hull_scene = Scene(train=masked, test=[], bounds=bounds, points=sparse)  # with masks: the points alone
    assert len(initial_gaussians(hull_scene, masked, 1000, 0, 0.3, torch.Generator().manual_seed(0))) == 150
