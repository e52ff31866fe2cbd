"""The Neural Merger (paper section 3.3): per-Gaussian softmax weights over views.

For each channel group (base color, roughness, metallic) a separate MLP (3 hidden layers of 128,
ReLU) reads the NeRF positional encoding of the Gaussian's position and the group's per-view values
(and, with `seen_input`, which views saw it), and outputs one logit per view; the three MLPs are kept
and evaluated layer by layer as one batch. Views in which the
Gaussian was not seen are either masked out before the softmax (`unseen="mask"`) or, as in the paper's
released code, filled with the mean of the views that saw it (`unseen="mean"`, softmax over all views);
either way the merged value is a convex combination of what the Gaussian received:

    h_g = f_theta(PE(p_g), m_g1 .. m_gV)        w_gv = softmax_v(h_gv)        m_g = sum_v w_gv m_gv

The last layer starts at zero, so before training the merger returns the plain average of the seen
views (the paper's "Proj. Average", its initialisation). With `softmax=False` (the paper's ablation)
the weights are 1/n_seen + h (`unconstrained="offset"`): the same starting point, but free to leave the convex
hull; or, with `unconstrained="raw"`, h itself from a last layer initialised as torch initialises any linear layer:
the released code's merger with its softmax taken out, which starts away from the average and whose weights need
not sum to one.
"""

from __future__ import annotations

import dataclasses
import math
import pickle
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from matspray.data.images import save_torch_atomic
from matspray.errors import RunError, SettingError, file_error
from matspray.material import GROUPS
from matspray.settings import setting

UNSEEN_RULES = ("mask", "mean")
UNCONSTRAINED_RULES = ("offset", "raw")
PRECISIONS = ("auto", "float32", "bfloat16")


def native_bfloat16_cpu() -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware (AVX512-BF16 or AMX tiles), where they run faster
    than float32; elsewhere they are emulated, and slower."""
    try:
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    except (AttributeError, RuntimeError):  # an older torch without the probes
        return False


def mlp_dtype(precision: str, device: torch.device) -> torch.dtype:
    """The dtype the merger's MLPs multiply in, for `precision` (MergerConfig) on `device`."""
    if precision == "bfloat16" or (precision == "auto" and (device.type == "cuda" or native_bfloat16_cpu())):
        return torch.bfloat16
    return torch.float32


@dataclass(frozen=True)
class MergerConfig:
    hidden: int = setting(128, "width of the merger's hidden layers")
    layers: int = setting(3, "hidden layers of each merger MLP")
    frequencies: int = setting(6, "NeRF positional-encoding octaves")
    softmax: bool = setting(True, "weights by a softmax over the views (off: the paper's ablation without it)")
    unconstrained: str = setting(
        "offset",
        'the weights without the softmax: "offset" (1/n_seen + the MLP\'s output, its last layer starting at zero: '
        'the projection average to start from) or "raw" (the output itself, from torch\'s default initialisation: '
        "the released code's merger with its softmax removed)",
    )
    seen_input: bool = setting(
        False,
        "the MLPs also read the seen mask [V]; off as in the paper (position and values only)",
    )
    unseen: str = setting(
        "mask",
        'views that did not see a Gaussian: "mask" (weight 0) or "mean" (filled with the mean of the views '
        "that did, weighted like any view; the paper's released code)",
    )
    precision: str = setting(
        "auto",
        'the MLPs\' arithmetic: "float32", "bfloat16" (autocast: matrix products in bfloat16, weights and the '
        'merge in float32) or "auto": bfloat16 on a CUDA device (tensor cores) and on a CPU with native '
        "bfloat16 (AVX512-BF16 or AMX), where refinement is bound by these products, float32 elsewhere "
        "(docs/defaults.md)",
    )

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise SettingError(
                "precision", f"unknown precision '{self.precision}'; choose one of {', '.join(PRECISIONS)}"
            )
        if self.unconstrained not in UNCONSTRAINED_RULES:
            raise SettingError(
                "unconstrained",
                f"unknown rule '{self.unconstrained}'; choose one of {', '.join(UNCONSTRAINED_RULES)}",
            )
        if self.unseen not in UNSEEN_RULES:
            raise SettingError("unseen", f"unknown rule '{self.unseen}'; choose one of {', '.join(UNSEEN_RULES)}")
        if self.hidden < 1 or self.layers < 1 or self.frequencies < 0:
            raise SettingError(
                "hidden",
                f"hidden and layers must be >= 1 and frequencies >= 0, got {self.hidden}, "
                f"{self.layers}, {self.frequencies}",
            )


def positional_encoding(x: Tensor, frequencies: int) -> Tensor:  # [N, 3] in ~[-1, 1] -> [N, 3 * (1 + 2F)]
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi  # [F]
    angles = x[:, :, None] * scales  # [N, 3, F]
    return torch.cat([x, torch.sin(angles).flatten(1), torch.cos(angles).flatten(1)], dim=-1)


def mlp(n_in: int, n_out: int, hidden: int, layers: int, zero_head: bool = True) -> nn.Sequential:
    blocks: list[nn.Module] = []
    width = n_in
    for _ in range(layers):
        # in place: a linear layer's backward does not read its output, so ReLU may overwrite it (no extra
        # [N, hidden] tensor per layer and step)
        blocks += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    head = nn.Linear(width, n_out)
    if zero_head:
        nn.init.zeros_(head.weight)
        nn.init.zeros_(head.bias)
    return nn.Sequential(*blocks, head)


def _widened(weight: Tensor, width: int) -> Tensor:  # [out, in] -> [out, width], zero columns appended
    return weight if weight.shape[1] == width else F.pad(weight, (0, width - weight.shape[1]))


def merge_weights(logits: Tensor, seen: Tensor, softmax: bool, unconstrained: str = "offset") -> Tensor:
    """Per-view weights [N, V] from logits [N, V]; views not seen (seen [N, V] False) get weight 0. Without the
    softmax, `unconstrained` (MergerConfig) says what the logits are: offsets from 1/n_seen, or the weights."""
    if softmax:
        masked = logits.masked_fill(~seen, float("-inf"))
        return torch.softmax(masked, dim=-1).nan_to_num(0.0)  # a row with no seen view gives zeros
    if unconstrained == "raw":
        return logits * seen
    n_seen = seen.sum(-1, keepdim=True).clamp_min(1)
    return (1.0 / n_seen + logits) * seen


def _layered(hidden: Tensor, layers: list[tuple[Tensor, Tensor]], product) -> Tensor:  # [..., N, in] -> [..., N, out]
    """An MLP's layers, `product(bias, hidden, weight [in, out])` each (torch.addmm or torch.baddbmm), ReLU between."""
    for i, (bias, weight) in enumerate(layers):
        hidden = product(bias, hidden, weight)
        if i < len(layers) - 1:
            # in place: the product's backward does not read its output, so ReLU may overwrite it (no extra
            # [..., N, hidden] tensor per layer and step)
            hidden = hidden.relu_()
    return hidden


def batched_products(device: torch.device) -> bool:
    """Whether the channel groups' MLPs run as one batched product per layer over the padded inputs: on a GPU, where
    every product is a kernel launch; on the CPU a product per group at its own width is faster (MKL's batched
    product ran slower than the same products one by one, and the padding is left out: docs/dev/demo-time.md)."""
    return device.type != "cpu"


class NeuralMerger(nn.Module):
    def __init__(self, n_views: int, bounds: Tensor, config: MergerConfig | None = None):
        """`bounds` [2, 3]: the object's box; positions are mapped to [-1, 1] inside it."""
        super().__init__()
        self.config = config or MergerConfig()
        self.n_views = int(n_views)
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32).clone())
        pe_dim = 3 * (1 + 2 * self.config.frequencies)
        per_view = [group.stop - group.start + int(self.config.seen_input) for group in GROUPS.values()]
        self.input_widths = [pe_dim + self.n_views * n for n in per_view]  # each group's own MLP input
        # one MLP per group, made (and initialised) one after the other, then kept layer by layer as batches: a
        # layer's weights [G, out, in] (the first layer's padded with zero columns to the widest group's input, which
        # the padded inputs meet: their gradient is 0, so they stay 0) and biases [G, 1, out], so that one batched
        # product can run every group's layer (`batched_products`)
        zero_head = self.config.softmax or self.config.unconstrained == "offset"
        mlps = [
            mlp(width, self.n_views, self.config.hidden, self.config.layers, zero_head=zero_head)
            for width in self.input_widths
        ]
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for linears in zip(*([m for m in sequence if isinstance(m, nn.Linear)] for sequence in mlps)):
            width = max(linear.in_features for linear in linears)
            self.weights.append(nn.Parameter(torch.stack([_widened(x.weight.detach(), width) for x in linears])))
            self.biases.append(nn.Parameter(torch.stack([x.bias.detach() for x in linears])[:, None]))
        groups = [g for g, group in enumerate(GROUPS.values()) for _ in range(group.stop - group.start)]
        channel_groups = torch.tensor(groups, device=self.bounds.device)  # [5] each channel's group
        self.register_buffer("channel_groups", channel_groups, persistent=False)

    def encode_positions(self, positions: Tensor) -> Tensor:  # [N, 3] -> [N, pe_dim]
        lo, hi = self.bounds[0], self.bounds[1]
        unit = 2.0 * (positions - lo) / (hi - lo).clamp_min(1e-8) - 1.0
        return positional_encoding(unit, self.config.frequencies)

    def group_inputs(
        self, positions: Tensor, masked_values: Tensor, seen: Tensor, encoded: Tensor | None = None
    ) -> Tensor:
        """The channel groups' MLP inputs [G, N, D]: group g's is PE(position), the group's per-view values
        (`masked_values`: 0 where unseen, or filled by `fill_unseen`) and, with `seen_input`, the seen mask, padded
        with zeros to the widest group's D (the padded inputs meet zero weights). Fixed for frozen
        Gaussians, so callers may keep it."""
        if masked_values.shape[1] != self.n_views or seen.shape != masked_values.shape[:2]:
            raise RunError(f"the merger was built for {self.n_views} views but got values for {masked_values.shape[1]}")
        encoded = self.encode_positions(positions) if encoded is None else encoded
        seen_part = [seen.to(masked_values.dtype)] if self.config.seen_input else []
        inputs = [
            torch.cat([encoded, masked_values[:, :, group].flatten(1), *seen_part], dim=-1) for group in GROUPS.values()
        ]
        width = max(x.shape[-1] for x in inputs)
        return torch.stack([F.pad(x, (0, width - x.shape[-1])) for x in inputs])

    def merge(self, inputs: Tensor, masked_values: Tensor, seen: Tensor, return_weights: bool = False):
        """Merged materials [N, 5] from `group_inputs` [G, N, D] and the per-view values [N, V, 5] (0 where unseen) /
        seen [N, V]; with `return_weights` also the weights {group: [N, V]}."""
        device = masked_values.device
        # float64 inputs (gradient checks) keep their precision
        lower = masked_values.dtype == torch.float32 and mlp_dtype(self.config.precision, device) == torch.bfloat16
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=lower):
            if batched_products(device):
                logits = self._batched_logits(inputs)
            else:
                logits = torch.stack([self._group_logits(g, inputs[g]) for g in range(len(self.input_widths))])
        logits = logits.to(masked_values.dtype)  # [G, N, V]: bfloat16 back to float32
        w = merge_weights(logits, seen, self.config.softmax, self.config.unconstrained)  # [G, N, V]
        channel_weights = w.index_select(0, self.channel_groups).permute(1, 2, 0)  # [N, V, 5]
        # unconstrained weights (no softmax) can leave [0, 1]; with softmax only rounding can: keep materials valid
        out = (channel_weights * masked_values).sum(1).clamp(0.0, 1.0)
        return (out, dict(zip(GROUPS, w.unbind(0)))) if return_weights else out

    def _batched_logits(self, inputs: Tensor) -> Tensor:  # [G, N, D] -> [G, N, V]
        """Every group's MLP at once, one batched product per layer (the padding included)."""
        layers = [(biases, weights.transpose(1, 2)) for weights, biases in zip(self.weights, self.biases)]
        return _layered(inputs, layers, torch.baddbmm)

    def _group_logits(self, g: int, inputs: Tensor) -> Tensor:  # [N, D] -> [N, V]
        """Group g's MLP, a product per layer at the group's own input width (its first layer leaves out the
        padding)."""
        width = self.input_widths[g]
        layers = [
            (biases[g, 0], (weights[g, :, :width] if i == 0 else weights[g]).t())
            for i, (weights, biases) in enumerate(zip(self.weights, self.biases))
        ]
        return _layered(inputs[:, :width], layers, torch.addmm)

    def forward(
        self,
        positions: Tensor,
        values: Tensor,
        seen: Tensor,
        return_weights: bool = False,
        encoded: Tensor | None = None,
    ):
        """Merge per-view values.

        positions: [N, 3]; values: [N, V, 5] (base color rgb, roughness, metallic; anything where unseen);
        seen: [N, V] bool; encoded: `encode_positions(positions)` when the caller keeps it (fixed Gaussians).
        Returns merged materials [N, 5] (and the weights {group: [N, V]}).
        """
        masked, seen = prepare_values(values, seen, self.config.unseen)
        return self.merge(self.group_inputs(positions, masked, seen, encoded), masked, seen, return_weights)


def projection_average(values: Tensor, seen: Tensor) -> Tensor:  # [N, V, 5], [N, V] -> [N, 5]
    """The paper's "Proj. Average": mean of the per-view values over the views that saw the Gaussian."""
    n_seen = seen.sum(-1, keepdim=True).clamp_min(1)
    return (values * seen[..., None]).sum(1) / n_seen


def view_gains(
    values: Tensor, seen: Tensor, rounds: int = 2, min_value: float = 0.02
) -> Tensor:  # [N, V, 5], [N, V] -> [V, 3]
    """Each view's base-colour gain (per RGB channel) against the multi-view average: the median, over the Gaussians
    the view saw, of its value / the Gaussians' average, in log space; normalised to a geometric mean of 1 over the
    views that voted, so that the overall brightness stays the predictions'. A predictor whose batches differ in
    exposure or white balance shows as gains away from 1. `rounds` re-estimates the average from the aligned values;
    Gaussians darker than `min_value` in some channel do not vote. A view that saw no voting Gaussian keeps gain 1."""
    base = values[..., :3]  # [N, V, 3]
    log_gain = torch.zeros(values.shape[1], 3, dtype=values.dtype, device=values.device)  # [V, 3]
    for _ in range(rounds):
        aligned = base / log_gain.exp()  # [N, V, 3]
        average = (aligned * seen[..., None]).sum(1) / seen.sum(1, keepdim=True).clamp_min(1)  # [N, 3]
        voting = seen & (average.amin(-1, keepdim=True) > min_value) & (base.amin(-1) > 0)  # [N, V]
        ratio = (base.clamp_min(1e-6) / average[:, None, :].clamp_min(1e-6)).log()  # [N, V, 3]
        voted = voting.any(0)  # [V]
        for view in voted.nonzero().flatten().tolist():
            log_gain[view] = ratio[voting[:, view], view].median(0).values
        if voted.any():
            log_gain[voted] -= log_gain[voted].mean(0, keepdim=True)
    return log_gain.exp()


def align_view_gains(values: Tensor, gains: Tensor) -> Tensor:  # [N, V, 5], [V, 3] -> [N, V, 5] (or [..., 5], [3])
    """Per-view values with each view's base colour divided by its gain (`view_gains`), clamped to [0, 1]; also one
    view's 2D map [H, W, 5] with that view's gain [3]."""
    return torch.cat([(values[..., :3] / gains).clamp(0.0, 1.0), values[..., 3:]], dim=-1)


def fill_unseen(values: Tensor, seen: Tensor) -> Tensor:  # [N, V, 5], [N, V] -> [N, V, 5]
    """Per-view values with each unseen view replaced by the mean of the views that saw the Gaussian
    (the paper's released code); a Gaussian seen in no view gets zeros."""
    return torch.where(seen[..., None], values, projection_average(values, seen)[:, None, :])


def prepare_values(values: Tensor, seen: Tensor, unseen: str) -> tuple[Tensor, Tensor]:  # [N, V, 5], [N, V] -> same
    """What the merger reads and weights under the `unseen` rule: "mask" zeroes the unseen views (they
    get weight 0); "mean" fills them with the seen views' mean and lets every view count."""
    if unseen == "mean":
        return fill_unseen(values, seen), torch.ones_like(seen)
    return values * seen[..., None], seen


def clamp_to_seen_range(target: Tensor, values: Tensor, seen: Tensor) -> Tensor:  # [N, 5], [N, V, 5], [N, V] -> [N, 5]
    """`target` clamped, per Gaussian and channel, to the range its seen per-view values span: the values
    nearest `target` that a softmax merger can output. Exact for roughness and metallic (one channel: the convex hull is
    that range); for base color the per-channel box holds the RGB hull, so it bounds the reach from above.
    A Gaussian seen in no view keeps `target`."""
    lowest = torch.where(seen[..., None], values, torch.inf).amin(1)  # [N, 5]
    highest = torch.where(seen[..., None], values, -torch.inf).amax(1)
    clamped = torch.minimum(torch.maximum(target, lowest), highest)
    return torch.where(seen.any(1, keepdim=True), clamped, target)


def load_merger(path, n_views: int, bounds: Tensor, map_location="cpu") -> NeuralMerger:
    """A merger saved with `save_merger`; refuses a checkpoint made for a different number of views."""
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as exc:
        raise file_error(path, f"cannot read the merger checkpoint: {exc}") from None
    if not isinstance(state, dict) or "n_views" not in state or "state_dict" not in state:
        raise file_error(path, "is not a MatSpray merger checkpoint")
    if int(state["n_views"]) != int(n_views):
        raise file_error(
            path, f"merger was trained for {state['n_views']} views, this run has {n_views}", "delete it to retrain"
        )
    merger = NeuralMerger(n_views, bounds, MergerConfig(**state["config"]))
    try:
        merger.load_state_dict(batched_state(state["state_dict"]))
    except (RuntimeError, KeyError) as exc:
        raise file_error(
            path, f"merger weights do not fit: {str(exc).splitlines()[0]}", "delete it to retrain"
        ) from None
    return merger


def batched_state(state: dict) -> dict:
    """A merger's state dict in the batched layout (`NeuralMerger`); one saved with one MLP per group
    (`mlps.<group>.<index>.weight` and `.bias`, the layout before) is converted."""
    if not any(key.startswith("mlps.") for key in state):
        return state
    out = {key: value for key, value in state.items() if not key.startswith("mlps.")}
    positions = sorted({int(key.split(".")[2]) for key in state if key.startswith("mlps.")})  # the linear layers
    for layer, position in enumerate(positions):
        weights = [state[f"mlps.{group}.{position}.weight"] for group in GROUPS]
        width = max(weight.shape[1] for weight in weights)
        out[f"weights.{layer}"] = torch.stack([_widened(weight, width) for weight in weights])
        out[f"biases.{layer}"] = torch.stack([state[f"mlps.{group}.{position}.bias"] for group in GROUPS])[:, None]
    return out


def save_merger(merger: NeuralMerger, path) -> None:
    save_torch_atomic(
        {"n_views": merger.n_views, "config": dataclasses.asdict(merger.config), "state_dict": merger.state_dict()},
        path,
    )
