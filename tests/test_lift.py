import pytest
import torch

from matspray.data import Camera
from matspray.errors import ConfigError
from matspray.gaussians import Gaussians
from matspray.method.lift import LiftConfig, lift, supported_views, weighted_median, weighted_medians


def test_weighted_median_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    n_groups = 20
    group_ids = torch.randint(0, n_groups, (500,), generator=g)
    values = torch.randint(0, 256, (500,), generator=g).float() / 255  # PNG-like values
    counts = torch.randint(1, 5, (500,), generator=g)
    medians, has = weighted_median(group_ids, values, counts, n_groups + 2)
    assert not has[n_groups:].any() and (medians[n_groups:] == 0).all()
    for group in range(n_groups):
        members = group_ids == group
        expanded = values[members].repeat_interleave(counts[members])  # each sample as often as it hit
        assert has[group]
        assert medians[group] == torch.sort(expanded).values[(len(expanded) - 1) // 2]  # torch.median's lower median


def test_weighted_medians_of_all_channels_at_once_skip_entries_of_weight_zero():
    # the channels' medians in one sort are each channel's own; an entry of weight 0 is as if it were not there
    g = torch.Generator().manual_seed(1)
    group_ids = torch.randint(0, 15, (400,), generator=g)
    values = torch.randint(0, 256, (400, 5), generator=g).float() / 255
    counts = torch.randint(1, 6, (400,), generator=g) * (torch.rand(400, generator=g) > 0.3)
    medians, has = weighted_medians(group_ids, values, counts, 17)
    kept = counts > 0
    for channel in range(5):
        alone, has_alone = weighted_median(group_ids[kept], values[kept, channel], counts[kept], 17)
        assert torch.equal(medians[:, channel], alone) and torch.equal(has, has_alone)


def test_weighted_median_single_and_tied_values():
    medians, has = weighted_median(
        torch.tensor([0, 0, 0, 1]), torch.tensor([0.2, 0.9, 0.9, 0.4]), torch.tensor([1, 1, 1, 7]), 2
    )
    assert medians.tolist() == [0.8999999761581421, 0.4000000059604645] and has.all()


def hand_made_scene():
    """Camera on -z looking at +z. G0: opaque disk on the left; G1: small, right behind G0 (hidden);
    G2: opaque disk on the right; G3: a disk far outside the object mask (a floater)."""

    camera = Camera.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 0.8, 32, 32)
    means = torch.tensor([[-0.8, 0.0, 0.0], [-0.8, 0.0, 0.6], [0.8, 0.0, 0.0], [0.0, 1.45, 0.0]])
    scales = torch.tensor([[0.25, 0.25, 0.01], [0.05, 0.05, 0.05], [0.25, 0.25, 0.01], [0.1, 0.1, 0.01]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(4, 4).clone()
    opacity = torch.tensor([0.99, 0.99, 0.99, 0.99])
    gaussians = Gaussians(means, scales.log(), quats, torch.logit(opacity), torch.zeros(4, 1, 3))
    return gaussians, camera


def test_lifting_hand_made_scene_median_and_occlusion():
    gaussians, camera = hand_made_scene()
    pixels, _ = camera.project(gaussians.means)
    cols = torch.arange(32) + 0.5
    materials = torch.where((cols < 16)[None, :, None], torch.tensor(0.2), torch.tensor(0.8)).expand(32, 32, 5).clone()
    left_x, left_y = int(pixels[0, 0]), int(pixels[0, 1])
    materials[left_y, left_x] = 1.0  # one outlier inside G0's footprint: the median ignores it
    mask = torch.ones(32, 32)
    mask[int(pixels[3, 1]) - 3 :] = 0.0  # the bottom rows are background: G3 is a floater
    result = lift(
        gaussians,
        [camera, camera],
        [materials, materials],
        [mask, mask],
        ["a", "b"],
        LiftConfig(samples_per_side=4, visibility_threshold=0.5),
        progress=False,
    )
    assert result.kept.tolist() == [True, False, True, False]  # hidden and floater Gaussians removed
    assert torch.allclose(result.values[0], torch.full((2, 5), 0.2))
    assert torch.allclose(result.values[1], torch.full((2, 5), 0.8))
    assert result.seen.all()
    assert result.stats["gaussians_removed"] == 2


def test_a_view_that_only_glimpses_a_gaussian_does_not_count_as_seeing_it():
    """Camera a sees G0 (left disk) whole; camera b is turned so that only the edge of G0's footprint
    stays in the image: b's hits are a small share of a's, so b does not count (its median stays stored)."""

    gaussians, camera = hand_made_scene()
    glimpse = Camera.look_at([1.75, 0.0, -5.0], [1.75, 0.0, 0.0], [0.0, -1.0, 0.0], 0.8, 32, 32)
    materials = torch.full((32, 32, 5), 0.3)
    config = LiftConfig(samples_per_side=2)
    result = lift(
        gaussians, [camera, glimpse], [materials, materials], [None, None], ["a", "b"], config, progress=False
    )
    left = 0  # G0 is the first kept Gaussian
    hits_a, hits_b = result.hits[left].tolist()
    assert 0 < hits_b < 0.5 * hits_a
    assert result.seen[left].tolist() == [True, False]
    assert torch.allclose(
        result.values[left, 1], torch.full((5,), 0.3)
    )  # the glimpse's median is kept, just not counted
    everything = lift(
        gaussians,
        [camera, glimpse],
        [materials, materials],
        [None, None],
        ["a", "b"],
        LiftConfig(samples_per_side=2, min_support=0.0),
        progress=False,
    )
    assert everything.seen[left].tolist() == [True, True]
    assert supported_views(torch.tensor([[10, 4, 0], [0, 2, 1]]), 0.5).tolist() == [
        [True, False, False],
        [False, True, True],
    ]


def test_min_support_outside_zero_to_one_is_refused():

    with pytest.raises(ConfigError, match="min_support: must be in"):
        LiftConfig(min_support=1.5)


def test_the_median_reads_a_gaussians_core_and_a_tiny_gaussian_still_gets_a_value():
    """G0, a disk covering ~2 px per standard deviation, sits on a 0.2 spot (radius 2.5 px) inside a 0.8 surround:
    its 1-sigma core reads 0.2, while all the pixels it reaches (out to ~3.3 sigma) are mostly 0.8. G1 is too
    small for any ray (one per pixel) to pass through its core: it takes the median of its few hits instead."""

    camera = Camera.look_at([0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 0.8, 32, 32)
    focal = float(camera.K[0, 0])
    px = 5.0 / focal  # world units per pixel at the disks' depth
    target_pixel = torch.tensor([[20.5 + 0.3, 8.5]])  # 0.3 px from a pixel centre
    offset = (target_pixel - camera.K[:2, 2]) * px
    axis_signs = torch.sign(
        camera.project(torch.tensor([[1.0, 1.0, 0.0]]))[0][0] - camera.K[:2, 2]
    )  # image axes vs world x, y
    means = torch.zeros(2, 3)
    means[1, :2] = offset[0] * axis_signs
    pixels, _ = camera.project(means)
    assert torch.allclose(pixels[1], target_pixel[0], atol=1e-3)
    scales = torch.tensor([[2.0 * px, 2.0 * px, 0.01], [0.15 * px, 0.15 * px, 0.01]])
    gaussians = Gaussians(
        means,
        scales.log(),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(2, 4).clone(),
        torch.logit(torch.tensor([0.99, 0.99])),
        torch.zeros(2, 1, 3),
    )
    ys, xs = torch.meshgrid(torch.arange(32) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    spot = (xs - pixels[0, 0]) ** 2 + (ys - pixels[0, 1]) ** 2 <= 2.5**2
    materials = torch.where(spot[..., None], torch.tensor(0.2), torch.tensor(0.8)).expand(32, 32, 5).clone()
    materials[pixels[1, 1].long(), pixels[1, 0].long()] = 0.5  # the one pixel G1 reaches

    def lifted(footprint):
        config = LiftConfig(samples_per_side=1, footprint_sigmas=footprint)
        return lift(gaussians, [camera], [materials], [None], ["a"], config, progress=False)

    core, everything = lifted(1.0), lifted(None)
    assert core.kept.tolist() == [True, True] and core.seen.all()
    assert torch.allclose(core.values[0, 0], torch.full((5,), 0.2))
    assert torch.allclose(everything.values[0, 0], torch.full((5,), 0.8))
    assert torch.allclose(core.values[1, 0], torch.full((5,), 0.5)) and torch.equal(core.hits, everything.hits)


def test_a_footprint_of_zero_sigmas_is_refused():

    with pytest.raises(ConfigError, match="footprint_sigmas: must be > 0"):
        LiftConfig(footprint_sigmas=0.0)
