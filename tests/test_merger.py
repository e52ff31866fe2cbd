import pytest
import torch

from matspray.errors import DataError, RunError
from matspray.merger import (MergerConfig, NeuralMerger, clamp_to_seen_range, load_merger, positional_encoding, projection_average,
                             save_merger)

BOUNDS = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def random_inputs(n=50, v=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    positions = torch.rand(n, 3, generator=g) * 2 - 1
    values = torch.rand(n, v, 5, generator=g)
    seen = torch.rand(n, v, generator=g) > 0.4
    seen[:, 0] = True
    return positions, values, seen


def randomise(merger, seed=1):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in merger.parameters():
            p.copy_(torch.randn(p.shape, generator=g))


def test_positional_encoding_layout():
    x = torch.tensor([[0.5, -0.25, 0.0]])
    pe = positional_encoding(x, 2)
    assert pe.shape == (1, 15)
    assert torch.allclose(pe[0, :3], x[0])
    assert torch.allclose(pe[0, 3:9], torch.sin(torch.tensor([0.5, 1.0, -0.25, -0.5, 0.0, 0.0]) * torch.pi))


def test_untrained_merger_is_the_projection_average():
    positions, values, seen = random_inputs()
    merger = NeuralMerger(6, BOUNDS)
    assert torch.allclose(merger(positions, values, seen), projection_average(values, seen), atol=1e-6)


def test_output_is_convex_combination_ignoring_unseen_views():
    positions, values, seen = random_inputs()
    merger = NeuralMerger(6, BOUNDS)
    randomise(merger)
    merged, weights = merger(positions, values, seen, return_weights=True)
    for name, w in weights.items():
        assert torch.allclose(w.sum(-1), torch.ones(len(w)), atol=1e-5)
        assert (w >= 0).all() and (w[~seen] == 0).all()
    # each merged channel lies within the range of the seen values
    big = torch.where(seen[..., None], values, torch.tensor(-1.0)).amax(1)
    small = torch.where(seen[..., None], values, torch.tensor(2.0)).amin(1)
    assert (merged <= big + 1e-5).all() and (merged >= small - 1e-5).all()
    # changing a value in an unseen view changes nothing
    changed = values.clone()
    changed[~seen] = 123.0
    assert torch.allclose(merger(positions, changed, seen), merged)


def test_clamp_to_seen_range_is_the_nearest_value_a_softmax_merger_reaches():
    values = torch.tensor([[[0.2] * 5, [0.6] * 5, [0.9] * 5]])  # [1, 3, 5]; the 0.9 view is unseen
    seen = torch.tensor([[True, True, False]])
    target = torch.tensor([[0.1, 0.4, 0.7, 0.95, 0.2]])
    expected = torch.tensor([[0.2, 0.4, 0.6, 0.6, 0.2]])  # below -> lowest seen, above -> highest seen (not 0.9)
    assert torch.equal(clamp_to_seen_range(target, values, seen), expected)
    # whatever a trained softmax merger outputs is left where it is
    positions, values, seen = random_inputs()
    merger = NeuralMerger(6, BOUNDS)
    randomise(merger)
    with torch.no_grad():
        merged = merger(positions, values, seen)
    assert torch.allclose(clamp_to_seen_range(merged, values, seen), merged, atol=1e-6)
    # a Gaussian seen in no view keeps its target
    assert torch.equal(clamp_to_seen_range(target, values[:1, :3], torch.zeros(1, 3, dtype=torch.bool)), target)


def test_without_softmax_weights_are_unconstrained():
    positions, values, seen = random_inputs()
    merger = NeuralMerger(6, BOUNDS, MergerConfig(softmax=False))
    assert torch.allclose(merger(positions, values, seen), projection_average(values, seen), atol=1e-6)
    randomise(merger)
    _, weights = merger(positions, values, seen, return_weights=True)
    assert not torch.allclose(weights["base_color"].sum(-1), torch.ones(len(positions)), atol=1e-2)


def test_merger_learns_to_pick_the_right_view():
    torch.manual_seed(0)
    positions, values, seen = random_inputs(n=64, v=4)
    seen[:] = True
    target = values[:, 2]  # the truth is always what view 2 says
    merger = NeuralMerger(4, BOUNDS)
    opt = torch.optim.Adam(merger.parameters(), lr=1e-3)
    start = (merger(positions, values, seen) - target).abs().mean().item()
    for _ in range(300):
        loss = (merger(positions, values, seen) - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.3 * start


def test_checkpoint_round_trip_and_mismatch(tmp_path):
    merger = NeuralMerger(6, BOUNDS)
    randomise(merger)
    save_merger(merger, tmp_path / "merger.pt")
    positions, values, seen = random_inputs()
    back = load_merger(tmp_path / "merger.pt", 6, BOUNDS)
    assert torch.equal(back(positions, values, seen), merger(positions, values, seen))
    with pytest.raises(DataError, match="trained for 6 views, this run has 7"):
        load_merger(tmp_path / "merger.pt", 7, BOUNDS)
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(DataError, match="junk.pt"):
        load_merger(tmp_path / "junk.pt", 6, BOUNDS)
    with pytest.raises(RunError, match="built for 6 views"):
        merger(positions, values[:, :5], seen[:, :5])
