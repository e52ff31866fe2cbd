"""What baked shadows (`--set shadows=on`) cost a refinement step, part by part, on a small synthetic object.

The object is the demo's `composite` shape (block, ball, ring and rod, which shadow each other), its Gaussians flat
disks sampled on the mesh with random materials per part, lit by the built-in sky and seen by --views cameras on
the synthetic data's spiral. Its views are lifted and refined as a run refines them (variant `full`, learnable light,
learnable shading normals, backend numba), once without visibility and once with the visibility baked here.

Printed, in milliseconds (best of --repeats rounds of all the views each, and the median), with the same inputs in
both columns where a part exists in both:
  - bake: the shadow maps of every direction (seconds, once per run);
  - step: one whole refinement step (`step_losses`, backward, Adam), shadows off and on;
  - gaussian_shadows: the shadow factors of a view's Gaussians, forward, and forward + backward; and forward +
    backward taking turns with the formula it replaced, op by op (`tests/test_shadow_factors.py`'s reference), on
    the same inputs;
  - blend: the sparse blend of the per-Gaussian features (8 channels off, 14 on), forward + backward;
  - terms: the view's loss terms (the split-sum shading, SSIM, L1; shadowed on), forward + backward.

    python -m benchmarks.shadow_cost [--gaussians 12000] [--views 8] [--resolution 96] [--repeats 5] [--json FILE]

Run it under `MATSPRAY_THREADS=1` (one torch thread, and as many for numba): the figures are the CPU time of this
process (`time.process_time`), which on a shared machine moves less with the other processes' load than wall time
does (on one thread it is the compute time; a busy machine still slows it through shared caches and memory).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from matspray.data import View
from matspray.device import configure_threads
from matspray.gaussians import Gaussians
from matspray.material import ROUGHNESS_INDEX
from matspray.method.asset import Asset
from matspray.method.lift import LiftConfig, lift
from matspray.method.refine.loop import RefineConfig, RefineInputs, TrainingViews, refine, starting_light, step_losses
from matspray.method.refine.normals import ShadingNormals
from matspray.method.refine.sources import material_source
from matspray.method.refine.steps import adam as adam_optimizer
from matspray.method.refine.terms import TermOptions, view_terms
from matspray.method.relight import render_gbuffer, render_relit
from matspray.render.backend import rendering_with
from matspray.render.raster.gbuffer import FrozenViews
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.lights import builtin_envmap
from matspray.render.shade.visibility import (
    VisibilityConfig,
    bake_visibility,
    gaussian_shadows,
    light_cells,
    visibility_rows,
)
from matspray.synth.cameras import make_cameras
from matspray.synth.shapes import composite


# ------------------------------------------------------------------------------------------ the object
def composite_disks(count: int, seed: int = 0) -> tuple[Gaussians, torch.Tensor, torch.Tensor]:
    """`count` flat opaque disks on the composite object's surface, area-uniform, each part one random material;
    returns Gaussians, normals [N, 3], materials [N, 5]."""
    from tests.scenes import quaternion_z_to  # the disks' rotations, as the tests' disk sphere has them

    rng = np.random.default_rng(seed)
    parts = composite(rng)
    triangles = np.concatenate([p.vertices[p.faces] for p in parts])  # [F, 3, 3]
    part_of = np.concatenate([np.full(len(p.faces), i) for i, p in enumerate(parts)])
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    areas = 0.5 * np.linalg.norm(cross, axis=-1)
    faces = rng.choice(len(areas), size=count, p=areas / areas.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    tri = triangles[faces]
    means = tri[:, 0] + a[:, None] * (tri[:, 1] - tri[:, 0]) + b[:, None] * (tri[:, 2] - tri[:, 0])
    normals = cross[faces] / np.linalg.norm(cross[faces], axis=-1, keepdims=True)
    radius = 1.2 * math.sqrt(areas.sum() / count / math.pi)  # disks a little wider than their share of the area
    table = np.concatenate(
        [rng.uniform(0.1, 0.9, (len(parts), 3)), rng.uniform(0.2, 0.9, (len(parts), 1)), rng.random((len(parts), 1))],
        axis=-1,
    )
    table[:, 4] = (table[:, 4] > 0.6).astype(float)  # metal or not
    means_t, normals_t = torch.tensor(means, dtype=torch.float32), torch.tensor(normals, dtype=torch.float32)
    scales = torch.tensor([radius, radius, 0.05 * radius]).log().expand(count, 3).clone()
    gaussians = Gaussians(
        means_t, scales, quaternion_z_to(normals_t), torch.full((count,), 4.0), torch.zeros(count, 1, 3)
    )
    return gaussians, normals_t, torch.tensor(table[part_of[faces]], dtype=torch.float32)


def refine_inputs(count: int, views: int, resolution: int) -> tuple[RefineInputs, float]:
    """The object's views, its lifted materials and its visibility; and the bake's seconds."""
    gaussians, normals, materials = composite_disks(count)
    radius = float(gaussians.means.norm(dim=-1).max())
    cameras, _, _ = make_cameras(views, 0, radius, resolution, np.random.default_rng(1))
    light = EnvironmentMap.from_tensor(builtin_envmap("sky", 32), learnable=False).prefilter()
    asset = Asset(gaussians, materials, normals)
    photos, maps = [], []
    for i, camera in enumerate(cameras):
        rgb, alpha = render_relit(asset, camera, light)
        photos.append(
            View(f"r_{i:03d}", rgb / alpha[..., None].clamp_min(1e-4) * (alpha[..., None] > 1e-4), alpha, camera)
        )
        maps.append(render_gbuffer(asset, camera).materials.clamp(0, 1).detach())
    names, masks = [v.name for v in photos], [v.alpha for v in photos]
    lifted = lift(gaussians, cameras, maps, masks, names, LiftConfig(samples_per_side=2), progress=False)
    kept = lifted.kept
    geometry = Gaussians(
        *(getattr(gaussians, f)[kept] for f in ("means", "log_scales", "quats", "opacity_logits", "sh"))
    )
    start = time.process_time()
    visibility = bake_visibility(geometry, VisibilityConfig())
    bake = time.process_time() - start
    bounds = torch.stack([geometry.means.amin(0), geometry.means.amax(0)])
    inputs = RefineInputs(geometry, normals[kept], lifted.values, lifted.seen, photos, maps, bounds, visibility)
    return inputs, bake


# ------------------------------------------------------------------------------------------ timing
def timed_ms(function, calls: list, repeats: int) -> tuple[float, float]:
    """Best and median over `repeats` rounds of the mean milliseconds of `function(*args)` over `calls`."""
    for args in calls[:1]:
        function(*args)  # warm-up
    rounds = []
    for _ in range(repeats):
        start = time.process_time()
        for args in calls:
            function(*args)
        rounds.append(1000.0 * (time.process_time() - start) / len(calls))
    return min(rounds), statistics.median(rounds)


def interleaved(functions: dict, indices: list, repeats: int) -> dict[str, tuple[float, float]]:
    """`timed_ms` of each function over `indices`, the functions taking turns round by round (the same load)."""
    rounds = {name: [] for name in functions}
    for function in functions.values():
        function(indices[0])  # warm-up
    for _ in range(repeats):
        for name, function in functions.items():
            start = time.process_time()
            for i in indices:
                function(i)
            rounds[name].append(1000.0 * (time.process_time() - start) / len(indices))
    return {name: (min(r), statistics.median(r)) for name, r in rounds.items()}


class Refinement:
    """One refinement's state (`refine`'s set-up, without warm-up) for stepping a chosen view by hand."""

    def __init__(self, inputs: RefineInputs, frozen: FrozenViews, config: RefineConfig):
        self.config = config
        self.training = TrainingViews(inputs, frozen)
        self.normals = inputs.normals_over(config.normal_neighbours)
        means = inputs.gaussians.means
        self.source = material_source(config.kind, means, inputs.values, inputs.seen, inputs.bounds, config.merger)
        self.envmap = starting_light(config, None, means.device)
        self.shading = ShadingNormals(self.normals)
        with torch.no_grad():
            self.last = self.source()
        groups = [{"params": list(self.source.parameters()), "lr": 1e-3}, {"params": list(self.envmap.parameters())}]
        self.optimizer = adam_optimizer(groups + [{"params": list(self.shading.parameters()), "lr": 1e-3}])

    def step(self, index: int) -> None:
        t = self.training
        _, total = step_losses(index, t, self.source, self.last, self.normals, self.shading, self.envmap, self.config)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()

    def inputs_of(self, index: int) -> dict:
        """What the parts of view `index`'s step read, as the step makes them (leaves that take gradients)."""
        t, frozen = self.training, self.training.frozen
        step_light, _ = t.environment(self.envmap, False)
        # the same light as leaves: each part's backward stops at them
        light = type(step_light).from_tensors(
            step_light.layout, [x.detach().requires_grad_() for x in step_light.tensors()]
        )
        light.source = step_light.source.detach().requires_grad_()
        materials = self.source().detach().requires_grad_()
        normals = frozen.orient_normals(index, self.shading().detach()).requires_grad_()
        return {"light": light, "materials": materials, "normals": normals, "seen": frozen.visible_ids[index]}


def part_timings(run: Refinement, shadowed: bool, repeats: int) -> dict[str, tuple[float, float]]:
    """Milliseconds of each part of the views' steps (see the module's docstring)."""
    t = run.training
    views = range(len(t))
    found = {"step": timed_ms(run.step, [(i,) for i in views], repeats)}
    prepared = [run.inputs_of(i) for i in views]

    def shadows(i: int, backward: bool) -> None:
        p, seen = prepared[i], prepared[i]["seen"]
        v = t.visibility[seen]
        out = gaussian_shadows(
            v, p["normals"][seen], t.frozen.means[seen], p["materials"][seen], t.views[i].camera, p["light"]
        )
        if backward:
            out.sum().backward()

    if shadowed:
        from tests.test_shadow_factors import reference_shadow_factors  # the formula op by op, as it was

        def formula(i: int) -> None:  # `gaussian_shadows` with the old formula: the same inputs, forward + backward
            p, seen = prepared[i], prepared[i]["seen"]
            normals = F.normalize(p["normals"][seen], dim=-1, eps=1e-12)
            view_dirs = F.normalize(t.views[i].camera.center.to(normals) - t.frozen.means[seen], dim=-1)
            v = t.visibility[seen]
            cells = light_cells(p["light"], visibility_rows(v))
            reference_shadow_factors(
                v, normals, view_dirs, p["materials"][seen, ROUGHNESS_INDEX], cells
            ).sum().backward()

        pair = interleaved({"now": lambda i: shadows(i, True), "formula": formula}, list(views), repeats)
        found["gaussian_shadows forward+backward, interleaved"] = pair["now"]
        found["the formula op by op forward+backward, interleaved"] = pair["formula"]
        with torch.no_grad():
            found["gaussian_shadows forward"] = timed_ms(shadows, [(i, False) for i in views], repeats)
        found["gaussian_shadows forward+backward"] = timed_ms(shadows, [(i, True) for i in views], repeats)
    channels = 14 if shadowed else 8
    features = [torch.rand(len(t.frozen.means), channels, requires_grad=True) for _ in views]

    def blend(i: int) -> None:
        blended, _ = t.frozen.render(i, features[i])
        blended.sum().backward()

    found[f"blend ({channels} channels) forward+backward"] = timed_ms(blend, [(i,) for i in views], repeats)
    images = []
    for i in views:
        with torch.no_grad():
            blended, alpha = t.frozen.render(i, features[i])
        light = prepared[i]["light"]
        c = t.constants(i)
        options = TermOptions("l1", 0.05, False, True, 0.2, shadowed, light.layout, 0.25, type(light))
        tensors = (alpha, c.cover, c.view_dirs, c.photo, t.targets[i], c.surface, c.surface_weight, c.surface_count)
        images.append((options, blended.clone().requires_grad_(), tensors, c.view_dirs, light.tensors()))

    def terms(i: int) -> None:
        options, blended, tensors, normal_map, light = images[i]
        view_terms(options, blended, *tensors, normal_map, normal_map, *light).sum().backward()  # no flash

    found["terms forward+backward"] = timed_ms(terms, [(i,) for i in views], repeats)
    return found


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gaussians", type=int, default=12000)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    threads = configure_threads()
    torch.manual_seed(0)
    with rendering_with("numba"):
        inputs, bake = refine_inputs(args.gaussians, args.views, args.resolution)
        frozen = FrozenViews(inputs.gaussians, [v.camera for v in inputs.views])
        config = RefineConfig(iterations=1, light_warmup=0)
        rows = {}
        for shadowed in (False, True):
            run_inputs = inputs if shadowed else RefineInputs(**{**inputs.__dict__, "visibility": None})
            refine(run_inputs, config, progress=False, frozen=frozen)  # compiles and warms what a step runs
            rows["on" if shadowed else "off"] = part_timings(
                Refinement(run_inputs, frozen, config), shadowed, args.repeats
            )
    seen = sum(len(ids) for ids in frozen.visible_ids) / len(frozen)
    print(
        f"{len(inputs.gaussians)} Gaussians ({seen:.0f} seen per view), {args.views} views of {args.resolution} px, "
        f"{inputs.visibility.shape[1]} directions, torch threads {threads}"
    )
    print(f"bake: {bake:.2f} s (CPU)")
    print("| part | shadows off, CPU ms (best / median) | shadows on, CPU ms (best / median) |\n| --- | --- | --- |")
    names = list(dict.fromkeys([*rows["off"], *rows["on"]]))
    for name in names:
        cells = [f"{rows[m][name][0]:.2f} / {rows[m][name][1]:.2f}" if name in rows[m] else "" for m in ("off", "on")]
        print(f"| {name} | {cells[0]} | {cells[1]} |")
    if args.json is not None:
        record = {"args": {k: str(v) for k, v in vars(args).items()}, "bake_s": bake, "parts_ms": rows}
        args.json.write_text(json.dumps(record, indent=2))


if __name__ == "__main__":
    main()
