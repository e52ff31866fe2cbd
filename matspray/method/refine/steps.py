"""The step driver of refinement (`matspray.method.refine.loop`): a random training view per step, one optimizer
step each, and the check that losses and gradients stay finite.

On a GPU each host read of a device value waits for every queued kernel, so a check that reads a flag every step
would stall the queue every step. Instead each step records on the device whether its loss terms and gradients are
finite, keeping the figures of the first step where they were not (`FiniteRecord`), and the driver reads that record
only at the steps the caller names (log and checkpoint steps) and at the last one, where it raises NumericalError
naming the first bad step. From that step on the optimizer skips its updates (Adam's fused kernel reads the record's
flag on the device), so the parameters stay the last good ones: no later step trains from diverged values or feeds
NaN to a lookup, and whatever the caller saves before the error is from a good state.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.errors import NumericalError


def adam(groups: list[dict]) -> torch.optim.Adam:
    """Adam over parameter groups as one fused kernel per group: the per-parameter update is the same, but neither a
    launch per parameter nor a host read of each step count, and it can skip a step on a device flag (`optimize`)."""
    return torch.optim.Adam(groups, fused=True)


def check_finite(step: int, **terms: Tensor) -> None:
    for name, value in terms.items():
        if not torch.isfinite(value).all():
            raise NumericalError(
                f"refine step {step}: the {name} loss is {float(value)}; the last good checkpoint is kept"
            )


def nonfinite_gradient_error(step: int, groups: list[str]) -> NumericalError:
    return NumericalError(
        f"refine step {step}: non-finite gradient for the {', '.join(groups)}; the last good checkpoint is kept"
    )


def check_finite_gradients(step: int, param_groups) -> None:
    """A non-finite gradient would turn Adam's state (and every later step) into NaN without any loss showing it.
    param_groups: the optimizer's groups, each with a "name"."""
    bad = [
        group["name"]
        for group in param_groups
        if any(p.grad is not None and not torch.isfinite(p.grad).all() for p in group["params"])
    ]
    if bad:
        raise nonfinite_gradient_error(step, bad)


class FiniteRecord:
    """Whether every step so far had finite loss terms and gradients, and the figures of the first that did not,
    kept on the device: recording a step waits for nothing, only `check` reads it. Steps are recorded in order from
    `first_step`."""

    def __init__(self, param_groups, first_step: int = 1):
        self.params = [(group.get("name", "parameters"), p) for group in param_groups for p in group["params"]]
        device = self.params[0][1].device if self.params else torch.device("cpu")
        self.first_step = first_step
        self.clean = torch.ones((), dtype=torch.bool, device=device)  # no bad step yet
        self.clean_steps = torch.zeros((), dtype=torch.int64, device=device)  # steps recorded while clean
        self.bad = torch.zeros((), device=device)  # float 1 once a step was not finite (an optimizer's found_inf)
        self.figures: Tensor | None = None  # [T + P] the loss terms, then each gradient's largest |value|, of the
        # last clean step and then of the first bad one
        self.names: tuple[str, ...] = ()  # the T loss terms' names
        self.no_gradient = torch.zeros((), device=device)  # stands in for a parameter without a gradient

    @torch.no_grad()
    def record(self, terms: dict[str, Tensor]) -> None:
        """Note the next step's loss terms {name: []} and the parameters' gradients (after the backward pass); the
        terms' names stay the same from step to step."""
        if self.figures is not None and tuple(terms) != self.names:
            raise ValueError(f"the loss terms changed from {self.names} to {tuple(terms)} between steps")
        gradients = [self.no_gradient if p.grad is None else p.grad for _, p in self.params]
        # the largest |value| is NaN or inf exactly when some value is (a norm could overflow)
        figures = torch.stack([*terms.values(), *torch._foreach_norm(gradients, math.inf)])  # [T + P]
        if self.figures is None:
            self.figures, self.names = figures, tuple(terms)
        self.figures = torch.where(self.clean, figures, self.figures)
        self.clean = self.clean & (figures.abs().max() < math.inf)  # NaN and inf compare false
        self.clean_steps = self.clean_steps + self.clean
        self.bad = torch.where(self.clean, 0.0, 1.0)

    def check(self) -> None:
        """Raise NumericalError naming the first step whose loss or gradients were not finite (one host read)."""
        if bool(self.clean):
            return
        step, figures = self.first_step + int(self.clean_steps), self.figures.cpu()
        count = len(self.names)
        check_finite(step, **dict(zip(self.names, figures[:count])))
        bad = {name: None for (name, _), value in zip(self.params, figures[count:]) if not torch.isfinite(value)}
        raise nonfinite_gradient_error(step, list(bad))


def optimize(
    optimizer,
    n_views: int,
    steps: int,
    losses_of_view,
    generator,
    desc: str,
    progress: bool,
    on_step=None,
    check_at=None,
) -> None:
    """The step driver shared by the warm-up and the refinement: `steps` times, draw a random training view, take
    `losses_of_view(index)` -> (terms {name: []}, total []) and step the optimizer. `on_step(step, terms, bar)` runs
    after each step. Finiteness is read at the steps where `check_at(step)` is true and at the last: NumericalError
    then names the first step whose loss or gradients were not finite; the optimizer (fused Adam, `adam`) skips its
    updates from that step on."""
    record = FiniteRecord(optimizer.param_groups)
    indices = torch.randint(n_views, (steps,), generator=generator).tolist()  # the same draws as one per step
    bar = tqdm(range(1, steps + 1), desc=desc, disable=not progress)
    for step, index in zip(bar, indices):
        terms, total = losses_of_view(index)
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        record.record(terms)
        if step == steps or (check_at is not None and check_at(step)):
            record.check()
        optimizer.found_inf = record.bad  # read by Adam's fused kernel on the device (as a GradScaler's is)
        optimizer.step()
        if on_step is not None:
            on_step(step, terms, bar)
