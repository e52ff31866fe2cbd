"""The light interface: what shading, refinement and the asset ask of a light model.

A `Light` is a learnable (or fixed) module that split-sum shading reads through its prefiltered form:

- `prefilter(levels)` -> a `PrefilteredLight`, whose `lookup(directions, roughness, normals)` gives the specular
  radiance around each lobe direction and the irradiance E(n) at each normal (`deferred.shade_unit` reads only that);
- `prior()`: the regulariser refinement adds (weighted by `RefineConfig.light_tv_weight`);
- `map`: the light drawn as a lat-long map [H, 2H, 3] (what shadowing, previews and every reader of `envmap.exr` use);
- `save(path)` and the model's `load(path)`; `fixed()`: a copy that is not learnable.

Refinement prefilters a learnable light every step as one pure function of tensors (`step_function`), which
`matspray.device.Graphed` may capture as a CUDA graph; `PrefilteredLight.tensors()` and `from_tensors` carry the
prefiltered form through a captured graph's inputs.

A model is one subclass with a `kind` (its `refine.light_model` name), listed in `shade.models`.
`envmap.EnvironmentMap` (a lat-long map) and `sg.SGLight` (a mixture of spherical Gaussians) implement it.
"""

from __future__ import annotations

from typing import ClassVar

from torch import Tensor, nn


class PrefilteredLight:
    """What split-sum shading reads from a light: specular radiance by lobe direction and roughness, irradiance by
    normal. `prefilter()` returns itself, so shading takes a light or its prefiltered form alike."""

    source: Tensor | None = None  # [H, 2H, 3] the light as a lat-long map (for `render.visibility`), when kept

    def prefilter(self, levels=None) -> PrefilteredLight:
        return self

    def lookup(self, directions: Tensor, roughness: Tensor, normals: Tensor) -> tuple[Tensor, Tensor]:
        """`lookup_specular(directions, roughness)` and `lookup_diffuse(normals)`: [..., 3] each."""
        return self.lookup_specular(directions, roughness), self.lookup_diffuse(normals)

    def lookup_specular(self, directions: Tensor, roughness: Tensor) -> Tensor:  # [..., 3], [...] -> [..., 3]
        raise NotImplementedError

    def lookup_diffuse(self, normals: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        raise NotImplementedError

    @property
    def layout(self):
        """What `from_tensors` needs besides the tensors (hashable: part of a captured graph's key)."""
        raise NotImplementedError

    def tensors(self) -> tuple[Tensor, ...]:
        raise NotImplementedError

    @classmethod
    def from_tensors(cls, layout, tensors) -> PrefilteredLight:
        raise NotImplementedError


class Light(nn.Module):
    """A light model (see the module's text)."""

    kind: ClassVar[str]

    @property
    def learnable(self) -> bool:
        return any(p.requires_grad for p in self.parameters())

    @property
    def map(self) -> Tensor:  # [H, 2H, 3] linear radiance on a lat-long grid
        raise NotImplementedError

    @property
    def source(self) -> Tensor:  # [H, 2H, 3] what shadowing reads (`render.visibility.light_cells`)
        return self.map

    def radiance(self, directions: Tensor) -> Tensor:  # [..., 3] unit -> [..., 3]
        raise NotImplementedError

    def prefilter(self, levels=None) -> PrefilteredLight:
        raise NotImplementedError

    def prior(self) -> Tensor:  # [] the regulariser
        raise NotImplementedError

    def step_function(self, levels):
        """(function, options, tensors): `function(options, *tensors)` is pure and returns the prefiltered form's
        `tensors()`, then the light's lat-long map and its prior; `self.prefiltered_type` rebuilds the form."""
        raise NotImplementedError

    prefiltered_type: ClassVar[type[PrefilteredLight]]

    def fixed(self) -> Light:
        """A copy of the current light that is not learnable (detached)."""
        raise NotImplementedError

    def save(self, path) -> None:
        raise NotImplementedError

    @classmethod
    def load(cls, path) -> Light:
        raise NotImplementedError

    @classmethod
    def saved_at(cls, path) -> bool:
        """Whether `path` (an asset's `envmap.exr`) holds a light of this model."""
        raise NotImplementedError

    @classmethod
    def initial(cls, value: float, height: int, device=None) -> Light:
        """The learnable light refinement starts from: a uniform radiance `value`, at resolution `height` (the rows of
        its lat-long map)."""
        raise NotImplementedError
