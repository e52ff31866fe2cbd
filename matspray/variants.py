"""The method's variants (the paper's ablations), in one registry used by refinement, the CLI, the
evaluation and the tables.

  full          Neural Merger with softmax over views, trained with both losses, learns the light
  no-softmax    Neural Merger with unconstrained weights (the paper's softmax ablation)
  supervised    free per-Gaussian materials trained with the 2D-map loss only
  proj-average  the mean of the projected per-view values; no training at all
  no-prior      free per-Gaussian materials from an uninformed grey, trained with the PBR loss alone and a
                learnable light, no 2D maps at all: the R3DGS-like baseline of the paper's Table 1
"""

from __future__ import annotations

from dataclasses import dataclass

from matspray.errors import ConfigError


@dataclass(frozen=True)
class Variant:
    name: str
    label: str  # as the paper's tables write it
    source: str  # what produces the materials: "merger", "free" (per-Gaussian parameters) or "average"
    softmax: bool = True  # merger only: softmax over views (False: the paper's ablation)
    learns_light: bool = False  # trained with the PBR photometric loss and a learnable environment map
    uses_maps: bool = True  # reads the 2D material maps (lifted values, the 2D-map loss); False: needs no predictor

    @property
    def trains(self) -> bool:
        return self.source != "average"


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("full", "Full", "merger", softmax=True, learns_light=True),
        Variant("proj-average", "Proj. Average", "average"),
        Variant("supervised", "Supervised", "free"),
        Variant("no-softmax", "Without Softmax", "merger", softmax=False, learns_light=True),
        Variant("no-prior", "No prior (R3DGS-like)", "free", learns_light=True, uses_maps=False),
    )
}
VARIANT_NAMES = tuple(VARIANTS)
LABELS = {v.name: v.label for v in VARIANTS.values()}
ABLATION = ("full", "supervised", "proj-average")  # the paper's Table 2
SOFTMAX_ABLATION = ("full", "no-softmax")  # the paper's softmax ablation
BASELINE = "no-prior"  # the paper's Table 1 baseline: materials optimised per scene without a 2D prior
MAPLESS = tuple(v.name for v in VARIANTS.values() if not v.uses_maps)  # what a run without 2D maps can make


def get_variant(name: str) -> Variant:
    if name not in VARIANTS:
        raise ConfigError(f"unknown variant '{name}'; choose one of {', '.join(VARIANT_NAMES)}")
    return VARIANTS[name]


def variants_for_maps(requested: tuple[str, ...] | list[str] | None, has_maps: bool) -> tuple[str, ...]:
    """The variants a run refines: `requested`, or by default `full` (with 2D maps) or the variants that need none.
    Without maps, a requested variant that reads them is refused in one line."""
    if requested is None:
        return ("full",) if has_maps else MAPLESS
    for name in requested:
        if not has_maps and get_variant(name).uses_maps:
            raise ConfigError(
                f"variant '{name}' needs 2D material maps, and this run has none (--predictor none); "
                f"give a predictor (files:DIR, marigold, ...) or ask for {' / '.join(MAPLESS)}"
            )
    return tuple(requested)


def asset_stage(name: str) -> str:
    """Run-folder stage of a variant's asset: `asset/` for the full method, `asset-{variant}/` for ablations."""
    get_variant(name)
    return "asset" if name == "full" else f"asset-{name}"
