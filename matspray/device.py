"""Which torch device a command runs on, what a stage says when the device runs out of memory, and pure functions of
tensors run as CUDA graphs: one launch forward and one backward instead of the few hundred small kernels they
dispatch op by op, each of which would otherwise wait on Python to launch it.

`Graphed(function)` is called like the function, with its tensors and a hashable key of what else it depends on.
On a CUDA device it captures the function with `torch.cuda.make_graphed_callables`, once per key and per tensors'
shapes, dtypes and `requires_grad` (a graph replays exactly what it captured), and replays it after that. A capture
that fails is said once, and from then on the function runs op by op: the same values, more launches.

`capturing_with(capture)` replaces the capture (`capture(function, sample_tensors) -> callable`) for the code inside
the block and on every device: tests and `benchmarks.step_cost` run on the CPU through a stand-in that computes the
function as one operation each way.
"""

from __future__ import annotations

import os
import re
import sys
from contextlib import contextmanager
from functools import partial
from typing import Callable

import torch
from torch import Tensor

from matspray.errors import ConfigError, ResourceError, SettingError

LOWER_HINT = (
    "lower the image size (--downscale 2), use fewer views, or cap the Gaussians (--set geometry.max_gaussians=N)"
)


def resolve_device(name: str) -> torch.device:
    """`auto` (CUDA when available, else CPU), `cpu`, `cuda` or `cuda:N`, with a clear error otherwise."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise SettingError("device", f"unknown device '{name}'; use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        why = (
            "this torch build has no CUDA"
            if torch.version.cuda is None
            else "this machine has no CUDA GPU that torch sees"
        )
        raise SettingError(
            "device", f"{name}: {why}; use cpu, or a CUDA build of torch on a machine with an NVIDIA GPU"
        )
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise SettingError(
            "device", f"{name}: this machine has {torch.cuda.device_count()} CUDA device(s), numbered from 0"
        )
    if device.type not in ("cpu", "cuda"):
        raise SettingError("device", f"unsupported device '{name}'; use auto, cpu, cuda or cuda:N")
    return device


@contextmanager
def out_of_memory_as_error(what: str, device):
    """Running out of GPU (or host) memory inside the block becomes one ResourceError naming `what`, the size
    that failed and what to lower. Stages write their artifacts only when done, so nothing half-written is left."""
    try:
        yield
    except torch.OutOfMemoryError as exc:  # CUDA's allocator
        raise ResourceError(_out_of_memory(what, f"memory on {device}", str(exc))) from None
    except RuntimeError as exc:  # the CPU allocator says it in a RuntimeError
        if "DefaultCPUAllocator: can't allocate memory" not in str(exc) and "not enough memory" not in str(exc):
            raise
        raise ResourceError(_out_of_memory(what, "host memory", str(exc))) from None


def _out_of_memory(what: str, memory: str, message: str) -> str:
    return (
        f"{what}: out of {memory}{_tried(message)}; {LOWER_HINT}, "
        "then run the same command again (finished stages are reused)"
    )


def _tried(message: str) -> str:
    """' allocating 2.00 GiB' from an allocator's message, or ''."""
    match = re.search(r"(?:Tried to allocate|you tried to allocate)\s+([\d.]+\s*[KMGT]?i?B|\d+ bytes)", message)
    return f" allocating {match.group(1)}" if match else ""


def configure_threads(device: torch.device | None = None) -> int:
    """Torch's CPU threads: $MATSPRAY_THREADS when set, else torch's default (one per core), which is faster on an
    idle machine (docs/defaults.md). (Under a second CPU-bound process two threads fight over the
    cores; set MATSPRAY_THREADS=1 then.)"""
    if device is not None and device.type == "cuda":
        return torch.get_num_threads()
    value = os.environ.get("MATSPRAY_THREADS")
    if value is None:
        return torch.get_num_threads()
    try:
        threads = int(value)
    except ValueError:
        raise ConfigError(f"$MATSPRAY_THREADS must be a positive integer, got '{value}'") from None
    if threads < 1:
        raise ConfigError(f"$MATSPRAY_THREADS must be >= 1, got {threads}")
    torch.set_num_threads(threads)
    return threads


def host_to_device(values: torch.Tensor, device) -> torch.Tensor:
    """A CPU tensor on `device` without stalling the host: a copy to a GPU from ordinary (pageable) memory waits
    for the GPU's queue to drain; one from page-locked memory is queued like a kernel. The CPU tensor as is on the
    CPU."""
    device = torch.device(device)
    if device.type != "cuda":
        return values.to(device)
    return values.pin_memory().to(device, non_blocking=True)


_CAPTURE: list = [None]  # the capture `capturing_with` set, or None: CUDA graphs on a CUDA device


@contextmanager
def capturing_with(capture: Callable | None):
    """Within the block, `Graphed` functions made there capture with `capture(function, samples)` on any device
    (None: CUDA graphs on a CUDA device, op by op elsewhere)."""
    saved = _CAPTURE[0]
    _CAPTURE[0] = capture
    try:
        yield
    finally:
        _CAPTURE[0] = saved


def cuda_graph(function, samples: tuple[Tensor, ...]):
    """The default capture: `function` as a CUDA graph each way (inputs that reach no output allowed)."""
    return torch.cuda.make_graphed_callables(function, samples, allow_unused_input=True)


class Graphed:
    """`function(options, *tensors) -> Tensor | tuple[Tensor, ...]`, captured per `options` (hashable) and per the
    tensors' layout, then replayed. `graphs=False` always runs it op by op. `what` names it in the one line said when
    a capture fails."""

    def __init__(self, function, what: str, graphs: bool = True):
        self.function, self.what, self.graphs = function, what, graphs
        self.capture = _CAPTURE[0]
        self.captured: dict[tuple, Callable] = {}

    def __call__(self, options, *tensors: Tensor):
        run = partial(self.function, options)
        if not self.graphs or (self.capture is None and not tensors[0].is_cuda):
            return run(*tensors)
        key = (options, tuple((t.shape, t.dtype, t.device, t.requires_grad) for t in tensors))
        if key not in self.captured:
            # the capture runs the function on copies: the graph's own input buffers, which each replay fills
            samples = tuple(t.detach().clone().requires_grad_(t.requires_grad) for t in tensors)
            try:
                self.captured[key] = (self.capture or cuda_graph)(run, samples)
            except Exception as exc:  # a torch without graph support for some operation: slower, not wrong
                why = f"{type(exc).__name__}: {(str(exc).strip().splitlines() or [''])[0]}"
                print(f"{self.what} runs without CUDA graphs ({why})", file=sys.stderr)
                self.graphs = False
                return run(*tensors)
        return self.captured[key](*tensors)
