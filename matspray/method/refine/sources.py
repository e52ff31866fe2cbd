"""What produces a variant's per-Gaussian materials [N, 5]: one small class per kind of source, chosen once by the
variant's declared `source` (`matspray.presets.Variant`): the Neural Merger, free per-Gaussian parameters, or the
projection average."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from matspray.material import METALLIC_INDEX
from matspray.method.merger import MergerConfig, NeuralMerger, prepare_values, projection_average
from matspray.presets import Variant


class MaterialSource(nn.Module):
    """Per-Gaussian materials [N, 5] for one variant, from the lifted per-view values [N, V, 5] and which views saw
    each Gaussian [N, V]. A source without a merger makes them with `source_materials`."""

    def __init__(self, variant: Variant, values: Tensor, seen: Tensor, unseen: str = "mask"):
        super().__init__()
        self.variant = variant
        self.merger = None
        # unseen entries carry no information; a merger may fill them instead (the paper's rule)
        values, seen = prepare_values(values, seen, unseen)  # [N, V, 5], [N, V] what the source reads
        self.register_buffer("values", values)
        self.register_buffer("seen", seen)

    def forward(self, index: Tensor | None = None, return_weights: bool = False):
        """Materials [N, 5], or [K, 5] for the Gaussians `index` [K]; with `return_weights` also the merger's
        weights {group: [K, V]} (empty for a source without a merger)."""
        materials = self.source_materials(picker(index))
        return (materials, {}) if return_weights else materials

    def source_materials(self, pick) -> Tensor:
        raise NotImplementedError

    @classmethod
    def made(cls, variant: Variant, positions: Tensor, values: Tensor, seen: Tensor, bounds, merger_config):
        """The source from everything any source may read (`material_source`); this one reads the views' values."""
        return cls(variant, values, seen)

    def learning_rate(self, config) -> float:  # config: refine.loop.RefineConfig
        return config.merger_lr

    def min_coverage(self, config) -> float:  # config: refine.loop.RefineConfig
        """The pixels' worth of a view below which a Gaussian's materials are not made at a step: 0 for a source whose
        values cost nothing to read (every Gaussian the view shows learns)."""
        return 0.0

    @property
    def trainable(self) -> bool:
        return any(p.requires_grad for p in self.parameters())


def picker(index: Tensor | None):
    return (lambda t: t) if index is None else (lambda t: t.index_select(0, index))


class AverageSource(MaterialSource):
    """The projection average of the seen views (nothing to train)."""

    def source_materials(self, pick) -> Tensor:
        return projection_average(pick(self.values), pick(self.seen))


class FreeSource(MaterialSource):
    """Free per-Gaussian parameters (sigmoid of logits), starting from an uninformed grey."""

    def __init__(self, variant: Variant, values: Tensor, seen: Tensor):
        super().__init__(variant, values, seen)
        self.logits = nn.Parameter(torch.zeros(values.shape[0], values.shape[2], device=values.device))

    def source_materials(self, pick) -> Tensor:
        return torch.sigmoid(pick(self.logits))

    def start_metallic(self, value: float) -> None:
        """Every Gaussian's metallic starts at `value` in (0, 1) instead of the grey's 0.5."""
        with torch.no_grad():
            self.logits[:, METALLIC_INDEX] = math.log(value / (1.0 - value))  # the logit of the start

    def start_base_color(self, colours: Tensor) -> None:  # [N, 3] linear
        """Every Gaussian's base colour starts at `colours`, kept inside (0, 1) so that its logit is finite."""
        with torch.no_grad():
            self.logits[:, :3] = torch.logit(colours.to(self.logits).clamp(0.02, 0.98))

    def learning_rate(self, config) -> float:
        return config.supervised_lr


class MergerSource(MaterialSource):
    """The Neural Merger's weighted views (softmax or not, as the variant says)."""

    def __init__(self, variant: Variant, positions: Tensor, values: Tensor, seen: Tensor, bounds, config: MergerConfig):
        config = MergerConfig(**{**config.__dict__, "softmax": variant.softmax})
        merger = NeuralMerger(values.shape[1], bounds, config)  # made first: its initial weights draw from the seed
        super().__init__(variant, values, seen, config.unseen)
        self.merger = merger
        with torch.no_grad():  # geometry is frozen: the MLPs' inputs never change
            self.inputs = self.merger.group_inputs(positions, self.values, self.seen)  # [G, N, D]

    @classmethod
    def made(cls, variant: Variant, positions: Tensor, values: Tensor, seen: Tensor, bounds, merger_config):
        return cls(variant, positions, values, seen, bounds, merger_config)

    def min_coverage(self, config) -> float:
        return config.min_coverage  # the merger's work on the slivers of a view is spared

    def forward(self, index: Tensor | None = None, return_weights: bool = False):
        pick = picker(index)
        inputs = self.inputs if index is None else self.inputs.index_select(1, index)  # [G, K, D]
        return self.merger.merge(inputs, pick(self.values), pick(self.seen), return_weights)


SOURCES: dict[str, type[MaterialSource]] = {"merger": MergerSource, "free": FreeSource, "average": AverageSource}


def material_source(
    variant: Variant,
    positions: Tensor,  # [N, 3]
    values: Tensor,  # [N, V, 5]
    seen: Tensor,  # [N, V] bool
    bounds: Tensor,  # [2, 3]
    merger_config: MergerConfig,
) -> MaterialSource:
    """The source of `variant`'s materials: the class its declared `source` names."""
    return SOURCES[variant.source].made(variant, positions, values, seen, bounds, merger_config)
