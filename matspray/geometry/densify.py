"""Adaptive density control of 3DGS: clone small and split large Gaussians whose projected centres
receive large gradients, prune transparent or oversized ones, reset opacities now and then. With the run's 2D
material maps, Gaussians that straddle a material edge are split too (`matspray.geometry.material_edges`). In a
capture without masks, once the object region is known (`DensityControl.focus`), only the object's Gaussians grow."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from matspray.gaussians import Gaussians
from matspray.geometry.config import GeometryConfig
from matspray.geometry.material_edges import footprint_edges
from matspray.geometry.optim import GaussianOptimizer
from matspray.geometry.region import ObjectRegion
from matspray.render.output import RasterOutput

RESET_OPACITY = 0.01
MIN_FOCUS_GAUSSIANS, MIN_FOCUS_SHARE = 10, 0.005  # an object region holding fewer is not focused on
SPLIT_INTO = 2
SPLIT_SHRINK = 0.8 * SPLIT_INTO  # children are 1.6 times smaller than their parent (3DGS)


class DensityControl:
    """Running screen-space gradient statistics and the densify / prune / reset schedule."""

    def __init__(self, config: GeometryConfig, extent: float, num_gaussians: int, device=None):
        self.config, self.extent = config, float(extent)
        self.region: ObjectRegion | None = None  # the object region once focused: only its Gaussians grow
        self.reset_stats(num_gaussians, device)

    def reset_stats(self, num_gaussians: int, device=None) -> None:
        self.grad_sum = torch.zeros(num_gaussians, device=device)  # summed |d loss / d mean2d| (NDC units)
        self.count = torch.zeros(num_gaussians, device=device)  # views in which the Gaussian was visible
        self.max_radius = torch.zeros(num_gaussians, device=device)  # largest 3-sigma radius, fraction of the image
        self.edge_sum = torch.zeros(num_gaussians, device=device)  # summed material edge strength in its footprint

    def observe(self, out: RasterOutput, width: int, height: int, edges: Tensor | None = None) -> None:
        """Record one view's statistics; call after backward, with out.retain_screen_grads() done before.
        edges: the view's material edge levels [L, H, W] (`TrainingView.material_edges`), or None."""
        grads = out.screen_absgrads if self.config.absgrad else out.screen_grads
        if grads is None:
            raise RuntimeError(
                "DensityControl.observe: call out.retain_screen_grads() before backward"
                + (" (and render with absgrad)" if self.config.absgrad else "")
            )
        visible = out.visible
        gx, gy = grads.detach().unbind(-1)  # scaled by Python numbers: a tensor of them would be a copy to the device
        ndc = torch.stack([gx * (0.5 * width), gy * (0.5 * height)], dim=-1)
        # dense updates that add 0 where not visible: the same sums as indexing the visible ones, without the
        # three gathers and scatters of a boolean index every step
        self.grad_sum += torch.where(visible, ndc.norm(dim=-1).to(self.grad_sum), 0.0)
        self.count += visible
        radius = out.radii.detach().to(self.max_radius) / max(width, height)
        self.max_radius = torch.where(visible, torch.maximum(self.max_radius, radius), self.max_radius)
        if edges is not None and self.config.material_edge_threshold > 0:
            strength = footprint_edges(edges, out.means2d, out.radii).to(self.edge_sum)
            self.edge_sum += torch.where(visible, strength, 0.0)

    def step(self, iteration: int, optimizer: GaussianOptimizer, generator: torch.Generator) -> str:
        """Apply the schedule after optimisation step `iteration` (0-based); returns what it did ('' if nothing)."""
        c, done = self.config, iteration + 1
        events = []
        if done >= c.densify_until:
            return ""
        if done > c.densify_from and done % c.densify_every == 0:
            events.append(self.densify_and_prune(optimizer, generator, prune_large=done > c.opacity_reset_every))
        if done % c.opacity_reset_every == 0:
            opacities = optimizer.params["opacity_logits"].detach()
            reset = opacities.clamp(max=float(torch.logit(torch.tensor(RESET_OPACITY, device="cpu"))))
            if self.region is not None:  # the background keeps its opacities: it no longer grows back
                reset = torch.where(self.inside(optimizer.params["means"].detach()), reset, opacities)
            optimizer.replace_values("opacity_logits", reset)
            events.append("opacity reset")
        return ", ".join(events)

    def densify_and_prune(self, optimizer: GaussianOptimizer, generator: torch.Generator, prune_large: bool) -> str:
        c = self.config
        g = optimizer.gaussians().detach()
        n = len(g)
        seen = self.count.clamp_min(1)
        grads = torch.where(self.count > 0, self.grad_sum / seen, torch.zeros_like(self.grad_sum))
        inside = self.inside(g.means)
        threshold = c.grad_threshold if self.region is None else c.grad_threshold * c.focus_grad_scale
        # each Gaussian's score: its gradient, or its material edge strength brought to the gradient's threshold
        score, on_edge = grads, torch.zeros_like(inside)
        if c.material_edge_threshold > 0:
            edges = self.edge_sum / seen * (threshold / c.material_edge_threshold)  # [N]
            on_edge = inside & (edges >= threshold) & (edges > grads)
            score = torch.maximum(grads, edges)
        candidates = inside & (score >= threshold)
        budget = max(0, c.max_gaussians - n)
        if int(candidates.sum()) > budget:  # over the cap: only the strongest grow
            order = torch.argsort(torch.where(candidates, score, torch.full_like(score, -1.0)), descending=True)
            candidates = torch.zeros_like(candidates)
            candidates[order[:budget]] = True
        largest = g.scales.max(dim=-1).values
        # a copy in place would straddle the same edge: Gaussians on an edge are split into smaller ones
        clone = candidates & (largest <= c.percent_dense * self.extent) & ~on_edge
        split = candidates & ~clone
        children = split_gaussians(g.subset(split), generator)
        appended = concat([g.subset(clone), children])

        opacities = g.opacities
        prune = opacities < c.prune_opacity
        if prune_large:
            # the background, which no longer grows, keeps its large Gaussians: they draw the room coarsely, and
            # without them the object's Gaussians would stretch to cover it
            large = (self.max_radius > c.max_screen_fraction) | (largest > c.max_world_fraction * self.extent)
            prune |= large & inside
        keep = ~(prune | split)
        optimizer.edit(keep, appended)
        self.reset_stats(len(optimizer.params["means"]), grads.device)
        edge_note = f" ({int((split & on_edge).sum())} on material edges)" if c.material_edge_threshold > 0 else ""
        return (
            f"+{int(clone.sum())} cloned, +{len(children)} split from {int(split.sum())}{edge_note}, "
            f"-{int((prune & ~split).sum())} pruned"
        )

    def inside(self, means: Tensor) -> Tensor:  # [N, 3] -> [N] bool: in the object region (all before the focus)
        if self.region is None:
            return torch.ones(len(means), dtype=torch.bool, device=means.device)
        return self.region.contains(means).to(means.device)

    def focus(self, optimizer: GaussianOptimizer, region: ObjectRegion) -> str:
        """From now on only the Gaussians inside `region` grow; the background keeps its `background_budget` share of
        max_gaussians, those covering the most (opacity times the area of the two larger axes): a room in the
        photos is then drawn coarsely, and the budget goes to the object."""
        g = optimizer.gaussians().detach()
        inside = region.contains(g.means).to(g.means.device)
        held = int(inside.sum())
        if held < max(MIN_FOCUS_GAUSSIANS, MIN_FOCUS_SHARE * len(inside)):  # no object found: better no focus at all
            return f"object focus skipped: the {region.describe()} holds {held} of {len(inside)} Gaussians"
        self.region = region
        background = int((~inside).sum())
        budget = int(self.config.background_budget * self.config.max_gaussians)
        keep = torch.ones_like(inside)
        if background > budget:
            largest_two = g.scales.sort(dim=-1).values[:, 1:]
            cover = g.opacities * largest_two.prod(dim=-1)
            cover = torch.where(inside, math.inf, cover)  # the object's Gaussians are all kept
            keep[torch.argsort(cover)[: background - budget]] = False
            optimizer.edit(keep)
            self.reset_stats(len(optimizer.params["means"]), self.grad_sum.device)
        return (
            f"object focus: {held} Gaussians in the {region.describe()}, "
            f"{background} outside, {int((~keep).sum())} of those pruned"
        )


def split_gaussians(g: Gaussians, generator: torch.Generator) -> Gaussians:
    """SPLIT_INTO children per Gaussian, centred at samples of it, SPLIT_SHRINK times smaller."""
    if len(g) == 0:
        return g
    repeated = concat([g] * SPLIT_INTO)
    noise = torch.randn(repeated.means.shape, generator=generator, device="cpu").to(
        repeated.means
    )  # the same draws on every device
    offsets = (repeated.rotation_matrices() @ (noise * repeated.scales)[:, :, None])[..., 0]
    return Gaussians(
        repeated.means + offsets,
        repeated.log_scales - float(torch.log(torch.tensor(SPLIT_SHRINK, device="cpu"))),
        repeated.quats,
        repeated.opacity_logits,
        repeated.sh,
    )


def concat(parts: list[Gaussians]) -> Gaussians:
    return Gaussians(
        *(
            torch.cat([getattr(p, name) for p in parts])
            for name in ("means", "log_scales", "quats", "opacity_logits", "sh")
        )
    )


def stats_state(control: DensityControl) -> dict:
    region = None if control.region is None else control.region.to_json()
    return {
        "grad_sum": control.grad_sum,
        "count": control.count,
        "max_radius": control.max_radius,
        "edge_sum": control.edge_sum,
        "region": region,
    }


def load_stats_state(control: DensityControl, state: dict, device=None) -> None:
    control.grad_sum, control.count, control.max_radius = (
        state[name].to(device) for name in ("grad_sum", "count", "max_radius")
    )
    # checkpoints from before the material edges have none
    control.edge_sum = state.get("edge_sum", torch.zeros_like(control.grad_sum)).to(device)
    region = state.get("region")  # checkpoints from before the object focus have none
    control.region = None if region is None else ObjectRegion.from_json(region)
