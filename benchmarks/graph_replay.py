"""A CUDA graph's capture and replay, on any device: the stand-in that tests and `benchmarks.step_cost` capture
`matspray.device.Graphed` functions with on the CPU (`capturing_with(graph_stand_in)`).

It keeps what makes a replay differ from calling the function again (`torch.cuda.make_graphed_callables`):
  - the function is traced once, at capture (`make_fx`, as a graph is recorded once): Python runs only then, so a
    tensor the function reads from outside its arguments is the one it read at capture (a graph reads the same
    memory again), and a Python value is the one it had then;
  - the graph's inputs are static buffers (the samples `Graphed` captured with); a call copies its tensors into them,
    and the graph runs on the buffers only: a tensor not copied in is the stale one;
  - its outputs and its gradients are static buffers too: what a call returns is a view of them, which the next
    replay overwrites; the backward replays from the last forward's activations, whichever call made them.
For `benchmarks.step_cost`'s count a replay is what it dispatches on a GPU: the copies into its buffers and the
views of its outputs are counted, the graph's own operations are not (a replay is one launch; `OPAQUE` is set while
they run).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.fx.experimental.proxy_tensor import make_fx

OPAQUE = [False]  # within a replay: its operations are one launch, counted as one (benchmarks.step_cost)


class _Opaque:
    def __enter__(self):
        OPAQUE[0] = True

    def __exit__(self, *exc):
        OPAQUE[0] = False


class Replayed:
    """`function` captured on `samples` (the static input buffers; their `requires_grad` says which inputs get a
    gradient), then replayed by calling it with tensors of the same layout."""

    def __init__(self, function, samples: tuple[Tensor, ...]):
        self.inputs = samples
        with _Opaque(), torch.no_grad():
            self.graph = make_fx(function)(*(x.detach() for x in samples))  # Python runs here only
            outputs = self.graph(*(x.detach() for x in samples))
        self.single = isinstance(outputs, Tensor)
        outputs = (outputs,) if self.single else tuple(outputs)
        self.outputs = tuple(o.clone() for o in outputs)  # the static output buffers
        self.grad_outputs = tuple(torch.zeros_like(o) for o in outputs)
        self.grad_inputs = tuple(torch.zeros_like(x) if x.requires_grad else None for x in samples)
        self.activations: tuple[Tensor, ...] = ()  # the last forward's, as a graph's static activations

    def forward(self, inputs: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
        with torch.no_grad():  # copies a replay dispatches too: counted
            for static, given in zip(self.inputs, inputs):
                if static.data_ptr() != given.data_ptr():  # as make_graphed_callables: copy unless already there
                    static.copy_(given)
        with _Opaque(), torch.enable_grad():
            out = self.graph(*self.inputs)
            self.activations = (out,) if self.single else tuple(out)
            with torch.no_grad():
                for static, value in zip(self.outputs, self.activations):
                    static.copy_(value)
        return tuple(o.detach() for o in self.outputs)  # views of the buffers the next replay overwrites

    def backward(self, grads: tuple[Tensor | None, ...]) -> tuple[Tensor | None, ...]:
        with torch.no_grad():
            for static, given in zip(self.grad_outputs, grads):
                if given is not None and static.data_ptr() != given.data_ptr():
                    static.copy_(given)
        with _Opaque():
            pairs = [(o, g) for o, g in zip(self.activations, self.grad_outputs) if o.requires_grad]
            wanted = [x for x in self.inputs if x.requires_grad]
            found = iter(
                torch.autograd.grad(
                    [o for o, _ in pairs], wanted, [g for _, g in pairs], retain_graph=True, allow_unused=True
                )
            )
            with torch.no_grad():
                for static in self.grad_inputs:
                    value = None if static is None else next(found)
                    if static is not None:
                        static.copy_(value) if value is not None else static.zero_()
        return tuple(None if g is None else g.detach() for g in self.grad_inputs)

    def __call__(self, *inputs: Tensor):
        outputs = _Replay.apply(self, *inputs)
        return outputs[0] if self.single else outputs


class _Replay(torch.autograd.Function):
    @staticmethod
    def forward(ctx, replayed: Replayed, *inputs):
        ctx.replayed = replayed
        return replayed.forward(inputs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        return (None, *ctx.replayed.backward(grads))


def graph_stand_in(function, samples: tuple[Tensor, ...]) -> Replayed:
    """`Graphed`'s capture on any device: `function` captured on `samples` and replayed as a CUDA graph would be."""
    return Replayed(function, samples)
