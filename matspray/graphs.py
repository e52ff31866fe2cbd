"""Pure functions of tensors run as CUDA graphs: one launch forward and one backward instead of the few hundred small
kernels they dispatch op by op, each of which would otherwise wait on Python to launch it.

`Graphed(function)` is called like the function, with its tensors and a hashable key of what else it depends on.
On a CUDA device it captures the function with `torch.cuda.make_graphed_callables`, once per key and per tensors'
shapes, dtypes and `requires_grad` (a graph replays exactly what it captured), and replays it after that. A capture
that fails is said once, and from then on the function runs op by op: the same values, more launches.

`capturing_with(capture)` replaces the capture (`capture(function, sample_tensors) -> callable`) for the code inside
the block and on every device: tests and `benchmarks.step_cost` run on the CPU through a stand-in that computes the
function as one operation each way.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from functools import partial
from typing import Callable

import torch
from torch import Tensor

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
