"""G-buffers for `benchmarks.ceilings`' rows that split the gap from the lifted truth to the true G-buffer: an asset's
G-buffer at each test view with some of its parts (materials, normals, alpha) swapped for the truth's, shaded and
scored as `matspray.eval.run_eval.evaluate_asset` shades and scores an asset.

A row names the source of each part, in that order: "asset" (the asset's G-buffer) or "true" (the test view's true
maps, normals and mask); all "asset" is the asset's own figure, all "true" the shading ceiling.
"""

from __future__ import annotations

import torch

from matspray.errors import RunError
from matspray.eval.run_eval import ViewRenders, score_renders, unpremultiply
from matspray.material import stack, unstack
from matspray.method.relight import render_gbuffer
from matspray.render.shade.deferred import GBuffer, shade_gbuffer

SOURCES = ("asset", "true")  # where a part of a row's G-buffer comes from


def build_gbuffer(materials, normals, alpha, shadow=None) -> GBuffer:  # [H, W, 5], [H, W, 3], [H, W], [H, W, 6]
    """A G-buffer of straight (not premultiplied) `materials`, `normals` and coverage `alpha` (`shadow`: None =
    unshadowed)."""
    return GBuffer(*unstack(materials), normals, alpha, shadow)


def truth_parts(truth) -> tuple:  # -> materials [H, W, 5], normals [H, W, 3], alpha [H, W]
    """The true maps, normals and mask of one test view (a `run_eval.GroundTruth`), as G-buffer parts."""
    if truth.normals is None:
        raise RunError("a test view has no true normals ({view}_normal.exr); make the object with `matspray synth`")
    return stack(truth.basecolor, truth.roughness, truth.metallic), truth.normals, truth.mask


def mixed_gbuffer(sources: tuple, rendered: GBuffer, truth) -> GBuffer:
    """`rendered` (an asset's G-buffer at a test view) with the parts `sources` names "true" taken from `truth`.
    Its materials are already divided by its coverage (`GBuffer.from_accumulated`), so they pair with any alpha; where
    it covers nothing they are zero, and so are its normals. The asset's shadows stay."""
    if len(sources) != 3 or not set(sources) <= set(SOURCES):
        raise ValueError(f"sources: (materials, normals, alpha), each one of {SOURCES}; got {sources}")
    parts = {
        "asset": (rendered.materials, rendered.normals, rendered.alpha),
        "true": tuple(p.to(rendered.alpha) for p in truth_parts(truth)),
    }
    return build_gbuffer(*(parts[source][i] for i, source in enumerate(sources)), rendered.shadow)


def asset_gbuffers(asset, camera, lights: dict) -> dict:
    """{light name: `asset`'s GBuffer at `camera`}: with visibility each carries the shadows its light casts, else one
    G-buffer serves every light."""
    if asset.visibility is None:
        return dict.fromkeys(lights, render_gbuffer(asset, camera))
    return {name: render_gbuffer(asset, camera, light) for name, light in lights.items()}


def shaded_renders(gbuffers: dict, camera, lights: dict) -> ViewRenders:
    """What per-light G-buffers {light name: GBuffer} show at `camera`, each shaded under its light as
    `evaluate_asset` shades an asset's (straight colour; materials clamped to [0, 1])."""
    relit = {name: unpremultiply(shade_gbuffer(g, camera, lights[name]), g.alpha).cpu() for name, g in gbuffers.items()}
    g = next(iter(gbuffers.values()))  # the material channels are the same in every light's G-buffer
    maps = (g.base_color, g.roughness, g.metallic)
    return ViewRenders(relit, *(m.cpu().clamp(0, 1) for m in maps), g.alpha.cpu(), g.normals.cpu())


def gbuffer_row_summary(asset, views: list, truths: list, lights: dict, sources: tuple) -> dict:
    """The evaluation summary (`score_renders`) of `asset`'s G-buffer at every test view with the parts `sources`
    names "true" taken from the truth, under every held-out light."""

    def renders():
        for view, truth in zip(views, truths):
            camera = view.camera.to(asset.gaussians.device)
            with torch.no_grad():  # left before yielding: the consumer's grad mode stays its own
                gbuffers = asset_gbuffers(asset, camera, lights)
                rendered = shaded_renders(
                    {name: mixed_gbuffer(sources, g, truth) for name, g in gbuffers.items()}, camera, lights
                )
            yield rendered

    return score_renders(renders(), views, truths, list(lights), None)["summary"]
