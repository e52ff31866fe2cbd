"""Densification on the 2D material maps' edges (geometry.material_edge_threshold): the edge map against its
definition, the window a Gaussian reads, Gaussians on an edge split rather than cloned, and the pipeline that feeds
the maps in where it has them."""

from __future__ import annotations

import re
from dataclasses import replace

import pytest
import torch

from matspray.data.images import linear_to_srgb
from matspray.data.scene import Scene
from matspray.errors import SettingError
from matspray.geometry.config import preset
from matspray.geometry.densify import DensityControl
from matspray.geometry.material_edges import edge_levels, footprint_edges, material_edge_map, view_edge_levels
from matspray.geometry.optim import GaussianOptimizer
from matspray.geometry.train import train_geometry
from matspray.synth.analytic import analytic_views
from tests.test_geometry_parts import LRS, gaussians_from


def step_maps(size: int = 16) -> torch.Tensor:  # [H, W, 5]: base colour 0.2 | 0.8 (linear) left / right, metal below
    maps = torch.zeros(size, size, 5)
    maps[..., :3] = 0.2
    maps[:, size // 2 :, :3] = 0.8
    maps[..., 3] = 0.5
    maps[size // 2 :, :, 4] = 1.0
    return maps


def test_the_edge_map_is_the_largest_change_in_each_window_on_the_objects_interior():
    maps, mask = step_maps(), torch.zeros(16, 16)
    mask[2:14, 2:14] = 1.0
    edges = material_edge_map(maps, mask)
    # brute force: per channel max - min over each pixel's 3 x 3 window (base colour sRGB-encoded), largest channel,
    # where the whole window lies inside the mask
    channels = torch.cat([linear_to_srgb(maps[..., :3]), maps[..., 3:]], dim=-1)
    expected = torch.zeros(16, 16)
    for y in range(16):
        for x in range(16):
            rows, cols = slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2)
            window = channels[rows, cols].reshape(-1, 5)
            inside = bool((mask[rows, cols] > 0.5).all())
            expected[y, x] = (window.amax(0) - window.amin(0)).max() if inside else 0.0
    torch.testing.assert_close(edges, expected)
    assert edges[4, 4] == 0 and edges[7, 4] == 1.0  # flat inside; metal meets dielectric
    base_step = float(linear_to_srgb(torch.tensor(0.8)) - linear_to_srgb(torch.tensor(0.2)))
    assert edges[4, 8] == pytest.approx(base_step)  # only the base colour changes there, as it shows (sRGB)
    assert (edges[:3] == 0).all() and (edges[:, 13:] == 0).all()  # the silhouette is not an edge


def test_a_gaussian_reads_the_window_of_its_footprint_at_its_centre():
    edges = torch.zeros(32, 32)
    edges[16, 16] = 0.7  # one edge pixel
    levels = edge_levels(edges)
    means2d = torch.tensor([[18.5, 16.5], [18.5, 16.5], [18.5, 16.5], [24.5, 16.5], [16.2, 16.9]])
    radii = torch.tensor([3.0, 6.0, 2.0, 12.0, 1.0]) * 3  # 3-sigma pixels: 1-sigma 3, 6, 2, 12 and 1 px
    strength = footprint_edges(levels, means2d, radii)
    # 2 px from the edge: a 1-sigma of 2 px reads the 5 x 5 window (which holds it), of 3 px the 9 x 9 one;
    # 8 px away even the widest misses it; a 1-sigma of 1 px sitting on the pixel reads it (3 x 3)
    torch.testing.assert_close(strength, torch.tensor([0.7, 0.7, 0.7, 0.0, 0.7]))
    narrow = footprint_edges(levels, means2d[:1], torch.tensor([2.0]))  # 1-sigma 0.67 px: a pixel's blur at most
    assert narrow.item() == 0.0
    two_px = footprint_edges(levels, torch.tensor([[18.5, 16.5]]), torch.tensor([3.0 * 1.2]))  # 3 x 3: misses
    assert two_px.item() == 0.0


def test_view_edge_levels_bring_the_maps_to_the_views_size():
    mask = torch.ones(8, 8)
    big = view_edge_levels(step_maps(16), mask)
    assert big.shape == (3, 8, 8)
    torch.testing.assert_close(big, edge_levels(material_edge_map(step_maps(8), mask)))  # halved steps are steps


def test_gaussians_on_a_material_edge_are_split_into_smaller_ones():
    config = replace(preset("test"), grad_threshold=1e-3, percent_dense=0.01, max_gaussians=100)
    small = [[0.005] * 3] * 3  # small enough that a large gradient would clone them
    for threshold, count in ((0.3, 4), (0.0, 3)):
        g = gaussians_from([[0, 0, 0], [1, 0, 0], [2, 0, 0]], small, [0.5] * 3)
        optimizer = GaussianOptimizer(g, LRS)
        control = DensityControl(replace(config, material_edge_threshold=threshold), extent=1.0, num_gaussians=3)
        control.grad_sum, control.count = torch.tensor([0.0, 0.0, 5e-4]), torch.full((3,), 2.0)
        control.edge_sum = torch.tensor([1.2, 0.2, 0.0])  # #0 on an edge in both its views (0.6), #1 faintly (0.1)
        message = control.densify_and_prune(optimizer, torch.Generator().manual_seed(0), prune_large=False)
        assert len(optimizer.params["means"]) == count, message
        if threshold > 0:  # #0 split into two children 1.6 times smaller; #1 and #2 (gradient too small) kept
            assert "+0 cloned, +2 split from 1 (1 on material edges)" in message
            scales = optimizer.params["log_scales"].detach().exp()
            torch.testing.assert_close(scales[2:], torch.full((2, 3), 0.005 / 1.6))
            torch.testing.assert_close(optimizer.params["means"].detach()[:2, 0], torch.tensor([1.0, 2.0]))
        else:  # off: the edges recorded count for nothing
            assert "+0 cloned, +0 split from 0, -0 pruned" == message


def test_the_edges_compete_with_the_gradients_for_the_cap():
    config = replace(preset("test"), grad_threshold=1e-3, max_gaussians=5, material_edge_threshold=0.2)
    g = gaussians_from([[i, 0, 0] for i in range(4)], [[0.005] * 3] * 4, [0.5] * 4)
    optimizer = GaussianOptimizer(g, LRS)
    control = DensityControl(config, extent=1.0, num_gaussians=4)
    # as multiples of their thresholds: gradients 2, 3 (#1, #2); edge 0.8 / 0.2 = 4 (#3): room for one
    control.grad_sum, control.count = torch.tensor([0.0, 2e-3, 3e-3, 0.0]), torch.ones(4)
    control.edge_sum = torch.tensor([0.0, 0.0, 0.0, 0.8])
    message = control.densify_and_prune(optimizer, torch.Generator().manual_seed(0), prune_large=False)
    assert "split from 1 (1 on material edges)" in message and len(optimizer.params["means"]) == 5


def test_a_threshold_without_material_maps_is_refused(tmp_path):
    views, _ = analytic_views(2, 16)
    scene = Scene(train=views, test=[], bounds=torch.tensor([[-1.0] * 3, [1.0] * 3]))
    config = replace(preset("test"), material_edge_threshold=0.3)
    with pytest.raises(SettingError, match="material_edge_threshold: is 0.3, but no 2D material maps were given"):
        train_geometry(scene, config, tmp_path, progress=False)
    with pytest.raises(SettingError, match=r"material_edge_threshold: must be in \[0, 1\]"):
        replace(preset("test"), material_edge_threshold=1.5)


def test_the_pipeline_splits_on_its_predictors_maps_and_only_where_it_has_them(tiny_object, tmp_path, capsys):
    from matspray.method.config import build_config
    from matspray.method.pipeline import Pipeline

    config = build_config("test", predictor="simulated:dr", **{"geometry.material_edge_threshold": 0.05})
    with Pipeline(tiny_object, tmp_path / "run", config, progress=True, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().settings.material_edge_threshold == 0.05
        fp = pipeline.geometry_plan().fingerprint
        pipeline.geometry()
    # densification split Gaussians on the maps' edges (its lines name how many)
    on_edges = [int(n) for n in re.findall(r"\((\d+) on material edges\)", capsys.readouterr().out)]
    assert on_edges and sum(on_edges) > 0, on_edges
    record = (tmp_path / "run" / "geometry" / "stage.json").read_text()
    assert '"material_edge_threshold": 0.05' in record
    off = build_config("test", predictor="simulated:dr")
    with Pipeline(tiny_object, tmp_path / "off", off, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().fingerprint != fp
    # the maps' draws are part of what the geometry depends on
    other = replace(config, predictor_options={**config.predictor_options, "seed": 7})
    with Pipeline(tiny_object, tmp_path / "other", other, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().fingerprint != fp
    # without a predictor there are no maps: the switch is off, and the fingerprint is the one of a run without it
    none = build_config("test", predictor="none", **{"geometry.material_edge_threshold": 0.05})
    plain = build_config("test", predictor="none")
    with Pipeline(tiny_object, tmp_path / "none", none, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().settings.material_edge_threshold == 0.0
        fp_none = pipeline.geometry_plan().fingerprint
    with Pipeline(tiny_object, tmp_path / "plain", plain, progress=False, log=lambda _: None) as pipeline:
        assert pipeline.geometry_plan().fingerprint == fp_none
