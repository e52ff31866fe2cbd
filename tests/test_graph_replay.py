"""The CUDA-graph stand-in of `benchmarks.graph_replay` replays as a graph does, so that code captured by
`matspray.device.Graphed` and tested on the CPU meets what a replay does on a GPU: Python runs once, at capture (a
tensor read from outside the arguments is the capture's), the inputs are copied into static buffers, and outputs and
gradients are views of static buffers that the next replay overwrites. A stand-in that calls the function again
(the one before) passes all of the stale-input bugs below."""

from __future__ import annotations

import torch

from benchmarks.graph_replay import graph_stand_in
from matspray.device import Graphed, capturing_with


def captured(function) -> Graphed:
    with capturing_with(graph_stand_in):
        return Graphed(function, "a test function")


def scaled_sum(options, x, y):  # [] and [3]: two outputs, one with a gradient to x
    return (options * x * y).sum(), x.detach() * 2


def test_a_replay_gives_the_functions_values_and_gradients_for_new_inputs():
    graphed = captured(scaled_sum)
    for seed in range(3):  # the capture's inputs, then new ones copied into its buffers
        g = torch.Generator().manual_seed(seed)
        x, y = torch.rand(3, generator=g).requires_grad_(True), torch.rand(3, generator=g)
        total, doubled = graphed(1.5, x, y)
        (gradient,) = torch.autograd.grad(total, x)
        expected = scaled_sum(1.5, x, y)
        assert torch.equal(total, expected[0]) and torch.equal(doubled, expected[1])
        assert torch.equal(gradient, torch.autograd.grad(expected[0], x)[0])
    assert len(graphed.captured) == 1


SCALE = {"tensor": torch.tensor(2.0)}


def reads_a_global(options, x):  # a stale-input bug: a tensor the graph does not take as an argument
    return x * SCALE["tensor"]


def test_a_tensor_read_from_outside_the_arguments_is_the_one_read_at_capture():
    graphed, x = captured(reads_a_global), torch.ones(2)
    assert torch.equal(graphed(None, x), torch.full((2,), 2.0))
    SCALE["tensor"] = torch.tensor(5.0)  # a new tensor: a graph still reads the old one's memory
    try:
        assert torch.equal(reads_a_global(None, x), torch.full((2,), 5.0))
        assert torch.equal(graphed(None, x), torch.full((2,), 2.0))  # stale, as on a GPU
        SCALE["tensor"].fill_(7.0)  # and a change in place of that new tensor is not seen either
        assert torch.equal(graphed(None, x), torch.full((2,), 2.0))
    finally:
        SCALE["tensor"] = torch.tensor(2.0)


def test_an_output_kept_past_the_next_replay_is_overwritten():
    graphed = captured(scaled_sum)
    x = torch.ones(3, requires_grad=True)
    first, _ = graphed(1.0, x, torch.ones(3))
    kept = first.clone()
    graphed(1.0, x, torch.full((3,), 4.0))
    assert kept.item() == 3.0 and first.item() == 12.0  # the first call's output now holds the second's value


def test_a_backward_replays_the_last_forward_whichever_call_it_belongs_to():
    graphed = captured(scaled_sum)
    x = torch.ones(3, requires_grad=True)
    first, _ = graphed(1.0, x, torch.full((3,), 2.0))
    graphed(1.0, x, torch.full((3,), 3.0))
    (gradient,) = torch.autograd.grad(first, x)
    assert torch.equal(gradient, torch.full((3,), 3.0))  # op by op it would be 2: the first call's y


def test_inputs_are_copied_into_the_captures_buffers():
    graphed = captured(scaled_sum)
    x = torch.ones(3, requires_grad=True)
    graphed(1.0, x, torch.ones(3))
    (replayed,) = graphed.captured.values()
    y = torch.full((3,), 5.0)
    graphed(1.0, x, y)
    assert torch.equal(replayed.inputs[1], y) and replayed.inputs[1].data_ptr() != y.data_ptr()
