import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from matspray.errors import DataError, RunError
from matspray.material import GROUPS
from matspray.method.merger import (
    MergerConfig,
    NeuralMerger,
    align_view_gains,
    clamp_to_seen_range,
    load_merger,
    positional_encoding,
    projection_average,
    save_merger,
    view_gains,
)

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


def test_raw_weights_without_softmax_are_the_mlp_output_from_a_random_start():
    positions, values, seen = random_inputs()
    torch.manual_seed(0)
    # float32: the reference below multiplies in float32, where "auto" takes bfloat16 on a CPU with native bfloat16
    merger = NeuralMerger(6, BOUNDS, MergerConfig(softmax=False, unconstrained="raw", precision="float32"))
    out, weights = merger(positions, values, seen, return_weights=True)
    # the released code's layers without their softmax: no zero start, so not the projection average
    assert not torch.allclose(out, projection_average(values, seen), atol=1e-2)
    inputs = merger.group_inputs(positions, values * seen[..., None], seen)
    hidden = inputs
    for i, (w, b) in enumerate(zip(merger.weights, merger.biases)):
        hidden = torch.baddbmm(b, hidden, w.transpose(1, 2))
        hidden = hidden.relu() if i < len(merger.weights) - 1 else hidden
    assert torch.allclose(weights["base_color"], hidden[0] * seen, atol=1e-6)  # the weights are the logits, unseen 0
    assert weights["base_color"][~seen].abs().max() == 0


def test_softmax_merger_ignores_the_unconstrained_rule():
    positions, values, seen = random_inputs()
    for rule in ("offset", "raw"):
        merger = NeuralMerger(6, BOUNDS, MergerConfig(unconstrained=rule))
        assert torch.allclose(merger(positions, values, seen), projection_average(values, seen), atol=1e-6)


def test_unknown_unconstrained_rule_is_refused():
    with pytest.raises(Exception, match="unknown rule 'free'; choose one of offset, raw"):
        MergerConfig(unconstrained="free")


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


def gained_values(seed=0, n=3000, v=6, spread=0.2):
    """Per-view values of n Gaussians whose base colour every view sees times its own RGB gain [v, 3]."""
    generator = torch.Generator().manual_seed(seed)
    true = torch.rand(n, 3, generator=generator) * 0.6 + 0.2
    gains = torch.exp(torch.randn(v, 3, generator=generator) * spread)
    values = torch.rand(n, v, 5, generator=generator)
    values[..., :3] = true[:, None, :] * gains
    seen = torch.rand(n, v, generator=generator) > 0.3
    return values, seen, gains, true


def test_view_gains_recover_each_views_gain_up_to_one_factor_per_channel():
    values, seen, gains, _ = gained_values()
    estimated = view_gains(values, seen)  # [V, 3]
    assert torch.allclose(estimated.log().mean(0), torch.zeros(3), atol=1e-5)  # the brightness stays the predictions'
    relative = estimated / gains  # one common factor per channel: the geometric mean of the true gains
    assert torch.allclose(relative, relative[:1].expand_as(relative), rtol=2e-3)
    assert torch.allclose(relative[0], 1.0 / gains.log().mean(0).exp(), rtol=2e-3)


def test_view_gains_ignore_a_minority_of_wrong_values_and_leave_an_empty_view_at_one():
    values, seen, gains, _ = gained_values(seed=1)
    values[:300, 2, :3] = 0.95  # a tenth of view 2's values are a baked highlight
    seen[:, 5] = False  # view 5 saw nothing
    estimated = view_gains(values, seen)
    assert torch.equal(estimated[5], torch.ones(3))
    relative = estimated[:5] / gains[:5]
    assert torch.allclose(relative, relative[:1].expand_as(relative), rtol=0.03)


def test_aligned_values_agree_between_views_and_keep_roughness_and_metallic():
    values, seen, _, true = gained_values(seed=2)
    aligned = align_view_gains(values, view_gains(values, seen))
    base = aligned[..., :3]
    spread_before = (values[..., :3].amax(1) - values[..., :3].amin(1)).mean()
    assert (base.amax(1) - base.amin(1)).mean() < 0.02 * spread_before  # every view now says the same colour
    assert torch.equal(aligned[..., 3:], values[..., 3:])


def per_group_merge(merger, positions, values, seen):
    """The merge as one MLP per channel group, layer by layer (the layout before the batched one)."""
    masked = values * seen[..., None]
    encoded = merger.encode_positions(positions)
    merged = []
    for g, group in enumerate(GROUPS.values()):
        hidden = torch.cat([encoded, masked[:, :, group].flatten(1)], dim=-1)
        for layer, (weight, bias) in enumerate(zip(merger.weights, merger.biases)):
            hidden = torch.nn.functional.linear(hidden, weight[g][:, : hidden.shape[1]], bias[g, 0])
            hidden = hidden.relu() if layer < len(merger.weights) - 1 else hidden
        weights = torch.softmax(hidden.masked_fill(~seen, float("-inf")), dim=-1).nan_to_num(0.0)
        merged.append((weights[..., None] * masked[:, :, group]).sum(1))
    return torch.cat(merged, dim=-1).clamp(0.0, 1.0)


def test_the_batched_groups_merge_as_one_mlp_per_group():
    merger = NeuralMerger(6, BOUNDS, MergerConfig(precision="float32"))
    randomise(merger)
    with torch.no_grad():
        for p in merger.parameters():
            p.mul_(0.1)
    positions, values, seen = random_inputs()
    torch.testing.assert_close(merger(positions, values, seen), per_group_merge(merger, positions, values, seen))


def test_each_group_multiplies_its_own_inputs_on_the_cpu_and_merges_as_the_batched_products(monkeypatch):
    import matspray.method.merger as merger_module

    merger = NeuralMerger(6, BOUNDS, MergerConfig(precision="float32"))
    randomise(merger)
    with torch.no_grad():
        for p in merger.parameters():
            p.mul_(0.1)
        merger.weights[0][1:, :, 39 + 6 :] = 0.0  # the padding of the one-channel groups, as the merger keeps it
    positions, values, seen = random_inputs()
    merged = {}
    for batched in (False, True):  # a product per group (the CPU), one batched product per layer (a GPU)
        monkeypatch.setattr(merger_module, "batched_products", lambda device: batched)
        merger.zero_grad()
        with Products() as products:
            out = merger(positions, values, seen)
        out.square().sum().backward()
        merged[batched] = out, [p.grad.clone() for p in merger.parameters()]
        if batched:
            assert products.shapes == []  # no product per group
        else:  # the first layer's product of each group at its own width: no product over the padding
            assert [shapes[1][1] for shapes in products.shapes[:: len(merger.weights)]] == [39 + 6 * 3, 39 + 6, 39 + 6]
    torch.testing.assert_close(merged[False][0], merged[True][0])
    for per_group, one_batch in zip(merged[False][1], merged[True][1]):
        torch.testing.assert_close(per_group, one_batch)
    monkeypatch.undo()
    assert merger_module.batched_products(torch.device("cuda"))
    assert not merger_module.batched_products(torch.device("cpu"))


class Products(TorchDispatchMode):
    """The MLPs' layer products (addmm) run inside it: their operands' shapes (bias, mat1, mat2) and outputs' dtypes."""

    def __init__(self):
        super().__init__()
        self.shapes, self.dtypes = [], []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if func is torch.ops.aten.addmm.default:
            self.shapes.append([tuple(a.shape) for a in args[:3]])
            self.dtypes.append(out.dtype)
        return out


def test_a_checkpoint_with_one_mlp_per_group_loads(tmp_path):
    import dataclasses

    merger = NeuralMerger(6, BOUNDS)
    randomise(merger)
    widths = {"base_color": 39 + 6 * 3, "roughness": 39 + 6, "metallic": 39 + 6}
    state = {"bounds": merger.bounds}  # the layout before: mlps.<group>.<index in its Sequential>.weight / .bias
    for layer, (weight, bias) in enumerate(zip(merger.weights, merger.biases)):
        for g, name in enumerate(GROUPS):
            columns = widths[name] if layer == 0 else weight.shape[2]
            state[f"mlps.{name}.{2 * layer}.weight"] = weight[g, :, :columns].detach().clone()
            state[f"mlps.{name}.{2 * layer}.bias"] = bias[g, 0].detach().clone()
    config = dataclasses.asdict(merger.config)
    torch.save({"n_views": 6, "config": config, "state_dict": state}, tmp_path / "merger.pt")
    back = load_merger(tmp_path / "merger.pt", 6, BOUNDS)
    positions, values, seen = random_inputs()
    torch.testing.assert_close(back(positions, values, seen), merger(positions, values, seen))


def test_an_unknown_precision_is_refused():
    from matspray.errors import SettingError

    with pytest.raises(SettingError, match="unknown precision 'half'"):
        MergerConfig(precision="half")


def test_auto_precision_is_bfloat16_on_cuda_and_on_a_cpu_that_multiplies_it_natively(monkeypatch):
    from matspray.method import merger as merger_module
    from matspray.method.merger import mlp_dtype

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert mlp_dtype("float32", cpu) == torch.float32 and mlp_dtype("bfloat16", cuda) == torch.bfloat16
    assert mlp_dtype("float32", cuda) == torch.float32
    monkeypatch.setattr(merger_module, "native_bfloat16_cpu", lambda: True)
    assert mlp_dtype("auto", cpu) == torch.bfloat16 and mlp_dtype("auto", cuda) == torch.bfloat16
    monkeypatch.setattr(merger_module, "native_bfloat16_cpu", lambda: False)
    assert mlp_dtype("auto", cpu) == torch.float32 and mlp_dtype("auto", cuda) == torch.bfloat16


def test_a_bfloat16_merger_multiplies_in_bfloat16_and_merges_close_to_float32():
    positions, values, seen = random_inputs(n=200, v=8)
    merged, products = {}, {}
    for precision in ("float32", "bfloat16"):
        merger = NeuralMerger(8, BOUNDS, MergerConfig(precision=precision))
        randomise(merger)
        with torch.no_grad():
            for p in merger.parameters():
                p.mul_(0.1)  # logits of a few units, as a trained merger's
        with Products() as seen_dtypes:
            merged[precision], weights = merger(positions, values, seen, return_weights=True)
        products[precision] = seen_dtypes.dtypes[0]
        assert all(w.dtype == torch.float32 for w in weights.values())  # the merge itself stays float32
    assert products == {"float32": torch.float32, "bfloat16": torch.bfloat16}
    difference = (merged["bfloat16"] - merged["float32"]).abs()
    assert difference.max() < 0.02 and difference.mean() < 0.003
    float64 = NeuralMerger(8, BOUNDS, MergerConfig(precision="bfloat16")).double()
    assert float64(positions.double(), values.double(), seen).dtype == torch.float64  # gradient checks keep float64


def test_the_merged_materials_gradient_matches_finite_differences():
    # the MLPs' ReLUs work in place on their linear layers' outputs: backward must still see the right masks
    positions, values, seen = random_inputs(n=8, v=3)
    merger = NeuralMerger(3, BOUNDS, MergerConfig(hidden=8, frequencies=1)).double()
    randomise(merger)
    with torch.no_grad():
        for p in merger.parameters():
            p.mul_(0.3)
    names = [name for name, _ in merger.named_parameters()]

    def merged(*params):
        return torch.func.functional_call(merger, dict(zip(names, params)), (positions.double(), values.double(), seen))

    assert torch.autograd.gradcheck(merged, [p.detach().clone().requires_grad_(True) for p in merger.parameters()])
