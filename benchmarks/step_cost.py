"""What one unit of work dispatches: torch operations and host synchronisations per Gaussian Splatting step, per
refinement step and per lifted view, at the paper preset's settings on a tiny analytic object.

On a GPU each operation is (at least) one kernel launch and each host synchronisation empties the queue, so these
counts stand in for launch overhead on any machine. Counted with a TorchDispatchMode, which sees every operation
that reaches a kernel (autograd's backward ones too, composite operations as their parts):
  - operations: every dispatched torch operation;
  - kernels: the operations that compute (views, detach and other aliases excluded: they launch nothing);
  - host syncs: what waits for the device: `aten._local_scalar_dense` (`item`, `float`, `bool`, `int` of a
    tensor), operations whose output size depends on the data (`nonzero`, `unique`, `masked_select`, boolean
    indexing, `repeat_interleave` not told its output's size), and `.cpu()` / `.numpy()` / `.tolist()` of a tensor
    outside backend numba's kernels (which run on the CPU by design). On CUDA (`--device cuda`) torch's profiler
    also counts the CUDA runtime's calls that wait for the device (stream, device and event synchronisations,
    blocking copies: "cuda waits", gsplat's own included) and the kernel and graph launches.

Paths (`--path`):
  - `cpu`: backend numba with its compiled per-Gaussian work (SH colour, normals), what a CPU run does;
  - `gpu`: backend numba's rasterizer, but SH colour and normals by torch operations and the merger's groups in
    batched products, as on a CUDA device where gsplat rasterizes (gsplat's own launches, about ten per step, are
    not in the count);
  - on `--device cuda`, the run's own backend (gsplat when it loads).

    python -m benchmarks.step_cost [--path cpu gpu] [--units geometry refine lift] [--json FILE]

Per unit: the Gaussian Splatting steps between two progress reports (after densification, SH degree 3, normal
loss on); refinement steps of `full` between two log steps (the difference of two runs that differ only in their
step count, warm-up and set-up cancelled; path `gpu`: the loss terms and the light's prefiltering as CUDA graphs,
through the stand-in that runs each as one operation each way; path `cpu`: op by op); one view lifted with 16 x 16
rays per pixel.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

from benchmarks.graph_replay import OPAQUE, graph_stand_in
from matspray.data.scene import Scene
from matspray.device import capturing_with
from matspray.geometry import train as geometry_train
from matspray.geometry.densify import DensityControl
from matspray.geometry.init import initial_gaussians
from matspray.geometry.optim import GaussianOptimizer
from matspray.geometry.step import ImageTerms, RunningStats, TrainingView, training_step
from matspray.method.config import build_config
from matspray.method.lift import lift_view
from matspray.method.refine.loop import RefineInputs, refine
from matspray.render import numba as numba_package
from matspray.render.backend import rendering_with, resolve_backend
from matspray.synth.analytic import analytic_views

# outputs whose size depends on the data: the device must finish before the host can size them
DATA_SIZED = ("aten.nonzero", "aten._unique2", "aten.unique_dim", "aten.unique_consecutive", "aten.masked_select")
HOST_READS = ("cpu", "numpy", "tolist")
VIEW_LIKE = ("aten.detach", "aten.lift_fresh", "aten.alias", "aten._unsafe_view")


@dataclass
class Count:
    operations: int = 0
    kernels: int = 0
    syncs: int = 0
    by_operation: Counter = field(default_factory=Counter)
    sync_kinds: Counter = field(default_factory=Counter)
    cuda_syncs: int | None = None  # calls of the CUDA runtime that wait for the device (CUDA only)
    cuda_launches: int | None = None  # kernel and graph launches (CUDA only)

    def per(self, units: int) -> dict:
        return {
            "operations": self.operations / units,
            "kernels": self.kernels / units,
            "host_syncs": self.syncs / units,
            "cuda_syncs": None if self.cuda_syncs is None else self.cuda_syncs / units,
            "cuda_launches": None if self.cuda_launches is None else self.cuda_launches / units,
            "sync_kinds": {k: v / units for k, v in self.sync_kinds.most_common()},
            "top_operations": {k: v / units for k, v in self.by_operation.most_common(12)},
        }

    def minus(self, other: "Count") -> "Count":
        return Count(
            self.operations - other.operations,
            self.kernels - other.kernels,
            self.syncs - other.syncs,
            self.by_operation - other.by_operation,
            self.sync_kinds - other.sync_kinds,
            None if self.cuda_syncs is None else self.cuda_syncs - (other.cuda_syncs or 0),
            None if self.cuda_launches is None else self.cuda_launches - (other.cuda_launches or 0),
        )


def is_sync(name: str, args, kwargs=None) -> bool:
    if name == "aten._local_scalar_dense.default" or name.startswith(DATA_SIZED):
        return True
    if name.startswith("aten.repeat_interleave.Tensor"):  # its output's size is read first unless it is told
        return (kwargs or {}).get("output_size") is None
    if name.startswith("aten.index.Tensor"):  # boolean indexing runs nonzero inside the kernel
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ()))
    return False


class _Operations(TorchDispatchMode):
    def __init__(self, count: Count, without_numba: bool):
        super().__init__()
        self.count, self.without_numba = count, without_numba

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        count = self.count
        if OPAQUE[0] or (self.without_numba and _inside_numba()):  # stands in for gsplat's kernels: not counted
            return func(*args, **(kwargs or {}))
        count.operations += 1
        count.by_operation[name] += 1
        if not (func.is_view or name.startswith(VIEW_LIKE)):
            count.kernels += 1
        if is_sync(name, args, kwargs) and not _inside_numba():
            count.syncs += 1
            count.sync_kinds[name] += 1
        return func(*args, **(kwargs or {}))


class _HostReads(TorchFunctionMode):
    """`.cpu()`, `.numpy()` and `.tolist()` outside backend numba's kernels, which read CPU tensors by design."""

    def __init__(self, count: Count):
        super().__init__()
        self.count = count

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in HOST_READS and not _inside_numba():
            self.count.syncs += 1
            self.count.sync_kinds[f"Tensor.{name}"] += 1
        return func(*args, **(kwargs or {}))


NUMBA_FOLDER = str(Path(numba_package.__file__).parent)  # backend numba's package: its frames are compiled code's


def _inside_numba() -> bool:
    frame = sys._getframe(1)  # walked by hand: traceback.extract_stack reads every frame's source line, per operation
    while frame is not None:
        if frame.f_code.co_filename.startswith(NUMBA_FOLDER):
            return True
        frame = frame.f_back
    return False


CUDA_WAITS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy")
CUDA_LAUNCHES = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx", "cudaGraphLaunch")


@contextmanager
def counting(device: torch.device, without_numba: bool = False):
    """Count what the block dispatches (`without_numba`: not what backend numba's calls dispatch); yields the Count
    (filled when the block ends). On CUDA also the CUDA runtime's own record (torch's profiler): the calls that wait
    for the device, and the kernel and graph launches."""
    count = Count()
    if device.type != "cuda":
        with _HostReads(count), _Operations(count, without_numba):
            yield count
        return
    torch.cuda.synchronize(device)
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=activities) as profile:
        with _HostReads(count), _Operations(count, without_numba):
            yield count
        torch.cuda.synchronize(device)
    calls = Counter()
    for event in profile.events():
        calls[event.name] += 1
    count.cuda_syncs = sum(n for name, n in calls.items() if name in CUDA_WAITS) - 1  # less the one closing it
    count.cuda_launches = sum(n for name, n in calls.items() if name in CUDA_LAUNCHES)


@contextmanager
def as_on_a_gpu():
    """What a CUDA device does op by op while backend numba rasterizes: the Gaussians' normals by torch operations,
    and the merger's groups in one batched product per layer (SH colour stays one fused call each way, as gsplat's
    kernel is there)."""
    import matspray.geometry.normals as normals_module
    import matspray.method.merger as merger_module

    saved = normals_module.compiled_on_cpu, merger_module.batched_products
    normals_module.compiled_on_cpu = lambda device: False
    merger_module.batched_products = lambda device: True
    try:
        yield
    finally:
        normals_module.compiled_on_cpu, merger_module.batched_products = saved


# ------------------------------------------------------------------------------------------ the tiny object
def tiny_scene(device: torch.device, views: int = 6, resolution: int = 48) -> Scene:
    train, _ = analytic_views(views, resolution)
    return Scene(train=[v.to(device) for v in train], test=[], bounds=torch.tensor([[-1.0] * 3, [1.0] * 3]))


def trained_state(scene: Scene, device: torch.device, points: int):
    """The paper preset's optimizer, density control and running figures on `scene`, before any step."""
    config = build_config("paper", **{"geometry.resolution": 48, "geometry.init_points": points}).geometry
    generator = torch.Generator().manual_seed(0)
    extent = geometry_train.scene_extent(scene.train)
    initial = initial_gaussians(
        scene, scene.train, config.init_points, config.sh_degree, config.init_opacity, generator, config.init_scale
    ).to(device)
    optimizer = GaussianOptimizer(initial, geometry_train.learning_rates(config, extent))
    density = DensityControl(config, extent, len(initial), device)
    return config, optimizer, density, RunningStats(device), generator


def geometry_steps(device: torch.device, counter, graphs: bool, points: int = 2000) -> tuple[Count, int]:
    """The steps between two progress reports, after densification ended (SH degree 3, normal loss on)."""
    scene = tiny_scene(device)
    config, optimizer, density, running, generator = trained_state(scene, device, points)
    first = (config.densify_until // geometry_train.SYNC_EVERY + 1) * geometry_train.SYNC_EVERY  # a report's step
    warm = range(first, first + 3)
    window = range(first + 3, first + geometry_train.SYNC_EVERY - 1)  # done % SYNC_EVERY != 0 throughout

    targets = [TrainingView.of(view, masked=True) for view in scene.train]
    image_terms = ImageTerms(graphs=graphs, capture=None if device.type == "cuda" else graph_stand_in)

    def step(iteration: int) -> None:
        target = targets[iteration % len(targets)]
        training_step(optimizer, density, running, target, config, iteration, generator, image_terms)

    for iteration in warm:
        step(iteration)
    with counter() as count:
        for iteration in window:
            step(iteration)
    return count, len(window)


def random_refine_inputs(gaussians, views, device) -> RefineInputs:
    """Refinement's inputs for `gaussians` and `views` with random normals, lifted values and 2D maps (seen in every
    view): what a step costs does not depend on their values."""
    n, v = len(gaussians), len(views)
    generator = torch.Generator().manual_seed(1)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=-1).to(device)
    values = torch.rand(n, v, 5, generator=generator).to(device)
    targets = [torch.rand(x.height, x.width, 5, generator=generator).to(device) for x in views]
    bounds = torch.stack([gaussians.means.min(0).values, gaussians.means.max(0).values]).detach()
    seen = torch.ones(n, v, dtype=torch.bool, device=device)
    return RefineInputs(gaussians, normals, values, seen, views, targets, bounds)


def refine_inputs(device: torch.device, points: int = 2000) -> RefineInputs:
    scene = tiny_scene(device)
    _, optimizer, *_ = trained_state(scene, device, points)
    return random_refine_inputs(optimizer.gaussians().detach(), scene.train, device)


def refine_steps(
    device: torch.device, counter, graphs: bool = True, short: int = 12, long: int = 36
) -> tuple[Count, int]:
    """Steps of `full` at the paper preset's settings, logging only at the last step: two runs that differ in their
    step count, subtracted. `graphs`: the loss terms and the light's prefiltering as CUDA graphs on CUDA, through the
    stand-in elsewhere (one operation each way); else op by op."""
    inputs = refine_inputs(device)
    base = build_config("paper").refine
    capture = None if device.type == "cuda" or not graphs else graph_stand_in

    def run(iterations: int, warmup: int = 4) -> Count:
        config = type(base)(**{**base.__dict__, "iterations": iterations, "light_warmup": warmup, "log_every": 10_000})
        with counter() as count, capturing_with(capture):
            refine(inputs, config, progress=False, graphs=graphs)
        return count

    run(2, 2)  # warm up
    return run(long).minus(run(short)), long - short


def lift_one_view(device: torch.device, counter, samples_per_side: int = 16) -> tuple[Count, int]:
    inputs = refine_inputs(device)
    view = inputs.views[0]
    config = build_config("paper").lift
    lift_view(inputs.gaussians, view.camera, inputs.targets[0], view.alpha, config)  # warm up
    with counter() as count:
        lift_view(inputs.gaussians, view.camera, inputs.targets[0], view.alpha, config)
    assert config.samples_per_side == samples_per_side
    return count, 1


UNITS = {"geometry": geometry_steps, "refine": refine_steps, "lift": lift_one_view}
UNIT_NAMES = {"geometry": "per Gaussian Splatting step", "refine": "per refinement step", "lift": "per lifted view"}


def measure(unit: str, path: str, device: torch.device, graphs: bool | None = None, **sizes) -> dict:
    """{operations, kernels, host_syncs, ...} per unit of `unit` on `path` (cpu | gpu | the device's own). `graphs`
    (geometry and refine): the terms as CUDA graphs or not (default: on path cpu not, else so); `sizes`: the unit's
    own (refine_steps' `short` and `long`)."""
    torch.manual_seed(0)
    counter = partial(counting, device, without_numba=path == "gpu")
    options = dict(sizes)
    if unit in ("geometry", "refine"):
        options["graphs"] = path != "cpu" if graphs is None else graphs
    if device.type == "cuda":
        with rendering_with(resolve_backend("auto", device)):
            count, units = UNITS[unit](device, counter, **options)
    else:
        with rendering_with("torch" if path == "gpu" and unit == "lift" else "numba"):
            if path == "gpu":
                with as_on_a_gpu():
                    count, units = UNITS[unit](device, counter, **options)
            else:
                count, units = UNITS[unit](device, counter, **options)
    return count.per(units)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--units", nargs="+", choices=list(UNITS), default=list(UNITS))
    parser.add_argument("--path", nargs="+", choices=("cpu", "gpu"), default=["cpu", "gpu"])
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda: there the run's backend and torch's "
                        "profiler's record of CUDA waits and launches")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--top", action="store_true", help="also print the most frequent operations")
    args = parser.parse_args()
    device = torch.device(args.device)
    paths = ["cuda"] if device.type == "cuda" else args.path
    results = {}
    print(f"{'unit':<28} {'path':<5} {'operations':>10} {'kernels':>8} {'host syncs':>10} {'cuda waits':>10} "
          f"{'launches':>8}")  # fmt: skip
    for unit in args.units:
        for path in paths:
            figures = measure(unit, path, device)
            results[f"{unit}/{path}"] = figures
            cuda = "" if figures["cuda_syncs"] is None else f"{figures['cuda_syncs']:.1f}"
            launches = "" if figures["cuda_launches"] is None else f"{figures['cuda_launches']:.1f}"
            print(
                f"{UNIT_NAMES[unit]:<28} {path:<5} {figures['operations']:>10.1f} {figures['kernels']:>8.1f} "
                f"{figures['host_syncs']:>10.2f} {cuda:>10} {launches:>8}",
                flush=True,
            )
            if args.top:
                for name, value in figures["top_operations"].items():
                    print(f"      {value:8.1f} {name}")
                for name, value in figures["sync_kinds"].items():
                    print(f"      sync {value:8.2f} {name}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
