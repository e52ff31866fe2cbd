"""The training views of refinement: each view's frozen blending weights (`FrozenViews`), what its losses read that
stays the same from step to step (`ViewConstants`), and the estimated light's prefiltering per step
(`TrainingViews.environment`). `matspray.method.refine.loop` drives the steps over them."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.data.scene import View
from matspray.device import Graphed
from matspray.material import N_CHANNELS
from matspray.method.refine.camera_light import CameraLight, falloff
from matspray.method.refine.terms import view_terms
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.deferred import view_directions
from matspray.render.shade.envmap import DEFAULT_LEVELS
from matspray.render.shade.light import Light, PrefilteredLight


def light_prior(envmap: Light) -> Tensor:  # -> []
    """The light model's regulariser (`Light.prior`; a lat-long map's: the total variation of its log radiance)."""
    return envmap.prior()


# ------------------------------------------------------------------------------------------ one view
def frozen_views(inputs) -> FrozenViews:  # inputs: refine.loop.RefineInputs
    """The training views' frozen blending weights, rendered with the enclosing block's backend."""
    return FrozenViews(inputs.gaussians.detach(), [v.camera for v in inputs.views])


@dataclass(frozen=True)
class ViewConstants:
    """What the losses of one training view read that stays the same from step to step, made once per view."""

    mask: Tensor  # [H, W] the object's mask (ones without one)
    surface: Tensor  # [H, W] the mask where the frozen Gaussians cover over half of a pixel: where 2D maps count
    surface_weight: Tensor  # [H, W, 5] `surface` per material channel
    surface_count: Tensor  # [] its sum, at least 1
    cover: Tensor  # [H, W, 1] the coverage, clamped: blended materials over it are the G-buffer's
    view_dirs: Tensor  # [H, W, 3] unit, from the surface towards the camera (`deferred.view_directions`)
    photo: Tensor  # [H, W, 3] the photo over black, sRGB
    falloff: Tensor | None = None  # [H, W, 1] a camera light's (d0 / d)^2, on a view it lights (`camera_light`)

    @classmethod
    def of(cls, view: View, alpha: Tensor, flash: Tensor | None = None) -> ViewConstants:  # alpha [H, W]: coverage
        mask = view.alpha if view.alpha is not None else torch.ones(view.height, view.width, device=alpha.device)
        surface = mask * (alpha > 0.5)
        weight = surface[..., None].expand(*surface.shape, N_CHANNELS)
        return cls(
            mask,
            surface,
            weight,
            weight.sum().clamp_min(1.0),
            alpha.clamp_min(1e-6)[..., None],
            view_directions(view.camera, alpha.device, alpha.dtype),
            linear_to_srgb(view.image * mask[..., None]),
            flash,
        )


class TrainingViews:
    """The training views with their frozen blending weights, 2D maps and the Gaussians' shadowing."""

    def __init__(
        self,
        inputs,  # refine.loop.RefineInputs
        frozen: FrozenViews | None = None,
        graphs: bool = True,
        camera_light: CameraLight | None = None,
        lit: list[bool] | None = None,
    ):
        """`frozen`: the views' frozen blending weights when the caller keeps them (`frozen_views(inputs)`: the
        variants of one run share them); made here otherwise. `graphs=False`: the terms op by op everywhere.
        `camera_light`: the flash that lit the views `lit` says (`camera_light.lit_views`; None: none)."""
        self.frozen = frozen_views(inputs) if frozen is None else frozen
        self.views = inputs.views
        self.targets = inputs.targets
        self.visibility = inputs.visibility
        self.normal_maps = inputs.normal_maps
        self._constants: dict[int, ViewConstants] = {}
        # past the render, a step's terms and the light's prefiltering: CUDA graphs on a CUDA device
        self.terms = Graphed(view_terms, "refinement's loss terms", graphs)
        self.graphs = graphs
        self.lights: dict = {}  # a learnable light's prefiltering per model (`Light.step_function`), graphed
        self.camera_light = camera_light
        self.lit = list(lit) if camera_light is not None and lit is not None else [False] * len(self.views)

    def __len__(self) -> int:
        return len(self.views)

    def environment(self, envmap: Light | None, with_prior: bool) -> tuple[PrefilteredLight | None, Tensor | None]:
        """The environment's split-sum maps and, `with_prior`, its light prior [] (None without an environment). A
        learnable map is prefiltered at every step (one graph on a CUDA device), a fixed one once (`prefilter`)."""
        if envmap is None:
            return None, None
        if not envmap.learnable:
            return envmap.prefilter(), light_prior(envmap) if with_prior else None
        function, layout, tensors = envmap.step_function(DEFAULT_LEVELS)
        if function not in self.lights:
            self.lights[function] = Graphed(function, "refinement's prefiltered light", self.graphs)
        *parts, radiance, prior = self.lights[function](layout, *tensors)
        light = envmap.prefiltered_type.from_tensors(layout, parts)
        light.source = radiance
        return light, prior if with_prior else None

    def constants(self, index: int) -> ViewConstants:
        if index not in self._constants:
            with torch.no_grad():
                alpha = self.frozen.alphas[index]
                flash = self.camera_falloff(index) if self.lit[index] else None
                self._constants[index] = ViewConstants.of(self.views[index], alpha, flash)
        return self._constants[index]

    def camera_falloff(self, index: int) -> Tensor:  # -> [H, W, 1]
        """The camera light's (d0 / d)^2 at each pixel of view `index`, d the frozen Gaussians' blended distance."""
        centre = self.views[index].camera.center.to(self.frozen.means)
        distances = (self.frozen.means - centre).norm(dim=-1, keepdim=True)  # [N, 1]
        blended, alpha = self.frozen.render(index, distances)
        return falloff(blended[..., 0], alpha, self.camera_light.reference_distance)
