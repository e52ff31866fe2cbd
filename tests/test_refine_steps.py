import math

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from matspray.errors import NumericalError
from matspray.method.refine.steps import FiniteRecord, adam, optimize


def toy(bad_loss_at=None, bad_gradient_at=None):
    """A parameter fitted to 1, its optimizer and losses_of_view, with a NaN loss or gradient at one call."""
    weight = torch.nn.Parameter(torch.zeros(3))
    optimizer = adam([{"params": [weight], "lr": 0.1, "name": "toy weights"}])
    calls = []

    def losses_of_view(index: int):
        calls.append(index)
        loss = ((weight - 1.0) ** 2).sum()
        if len(calls) == bad_loss_at:
            loss = loss * math.nan
        if len(calls) == bad_gradient_at:
            loss = loss + (weight - weight.detach()).sqrt().sum()  # adds 0 to the loss, inf to the gradient
        return {"photo": loss}, loss

    return weight, optimizer, losses_of_view, calls


def test_a_nan_loss_is_reported_at_the_next_check_naming_its_step():
    weight, optimizer, losses_of_view, _ = toy(bad_loss_at=3)
    steps_done, after = [], {}

    def on_step(step, terms, bar):
        steps_done.append(step)
        after[step] = weight.detach().clone()

    with pytest.raises(NumericalError, match="refine step 3: the photo loss is nan; the last good checkpoint is kept"):
        optimize(
            optimizer, 4, 20, losses_of_view, torch.Generator().manual_seed(0), "toy", False, on_step=on_step,
            check_at=lambda step: step % 5 == 0,
        )  # fmt: skip
    assert steps_done == [1, 2, 3, 4]  # the check at step 5 raises before that step goes on
    assert torch.equal(after[4], after[2]) and torch.equal(weight.detach(), after[2])  # no update from step 3 on
    assert not torch.equal(after[2], after[1])


def test_a_non_finite_gradient_is_reported_naming_its_step_and_parameter():
    _, optimizer, losses_of_view, _ = toy(bad_gradient_at=2)
    with pytest.raises(NumericalError, match="refine step 2: non-finite gradient for the toy weights"):
        optimize(optimizer, 4, 3, losses_of_view, torch.Generator().manual_seed(0), "toy", False)  # the last step


def test_finite_steps_run_through_and_draw_the_views_as_one_draw_per_step():
    weight, optimizer, losses_of_view, calls = toy()
    generator = torch.Generator().manual_seed(7)
    optimize(optimizer, 5, 30, losses_of_view, generator, "toy", False, check_at=lambda step: True)
    expected = torch.Generator().manual_seed(7)
    assert calls == [int(torch.randint(5, (1,), generator=expected)) for _ in range(30)]
    assert torch.equal(generator.get_state(), expected.get_state())  # what the warm-up cache keeps
    assert (weight - 1.0).abs().max() < 0.5


class HostReads(TorchDispatchMode):
    """Counts the operations that read a tensor's value on the host (`item`, `bool`, `float`, ...)."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += func is torch.ops.aten._local_scalar_dense.default
        return func(*args, **(kwargs or {}))


def test_recording_a_step_does_not_read_the_device():
    weight = torch.nn.Parameter(torch.ones(2))
    record = FiniteRecord([{"params": [weight], "name": "w"}])
    weight.grad = torch.tensor([1.0, math.nan])
    with HostReads() as reads:
        record.record({"photo": torch.tensor(0.5)})
        record.record({"photo": torch.tensor(0.25)})
    assert reads.count == 0
    with pytest.raises(NumericalError, match="refine step 1: non-finite gradient for the w"):
        record.check()


def test_refinement_never_checkpoints_after_a_non_finite_step(monkeypatch):
    from benchmarks.step_cost import refine_inputs
    from matspray.method.refine import loop as refine_module
    from matspray.render.backend import rendering_with

    view_losses, calls = refine_module.view_losses, []

    def failing_view_losses(*args, **kwargs):
        terms = view_losses(*args, **kwargs)
        calls.append(1)
        if len(calls) == 50:
            terms["photo"] = terms["photo"] * math.nan
        return terms

    monkeypatch.setattr(refine_module, "view_losses", failing_view_losses)
    config = refine_module.RefineConfig(iterations=150, envmap_height=8, light_warmup=0, log_every=1000)
    checkpoints = []
    with rendering_with("numba"), pytest.raises(NumericalError, match="refine step 50: the photo loss is nan"):
        refine_module.refine(
            refine_inputs(torch.device("cpu"), points=300), config, progress=False,
            on_checkpoint=lambda step, *rest: checkpoints.append(step),
        )  # fmt: skip
    assert checkpoints == []  # the check before the checkpoint of step 100 raised
