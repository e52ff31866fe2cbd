"""Catching tensors made on the wrong device without a GPU.

On a GPU, a tensor that a factory makes without naming its device (`torch.zeros(n)`, `torch.tensor([...])`,
`torch.from_numpy(...)`) lands on the CPU beside CUDA tensors. Inside `stray_tensor_check()` such a tensor is made
on the "meta" device instead, which holds no data and follows CUDA's rules against the CPU (a 0-dim CPU tensor
mixes with it, anything larger raises): code run on the CPU under the check fails where it would fail on CUDA. And
every such call is recorded with the line of ours that made it, also where the stray tensor would have been mixed
in silently (a scalar) or moved on before use.

Not counted as strays: what the dataset readers (matspray/data/, but camera.py) make, since data is read on the
CPU and moved to the device once, by design; parameters that torch.nn layers make when built (a module is built, then
moved with `.to(device)`), random draws from an explicit (CPU) generator, which the project makes on the CPU on purpose
so that a seed draws the same numbers on every device, and `as_tensor` / `*_like` of a tensor, which keep its device.
Why not `torch.set_default_device("meta")`: it also sends `torch.as_tensor(cpu_tensor)` to meta, which CUDA does not.
"""

from __future__ import annotations

import sys
import traceback
from contextlib import contextmanager

import torch
from torch.overrides import TorchFunctionMode

FACTORIES = {
    torch.zeros,
    torch.ones,
    torch.empty,
    torch.full,
    torch.rand,
    torch.randn,
    torch.randint,
    torch.randperm,
    torch.arange,
    torch.linspace,
    torch.logspace,
    torch.eye,
    torch.tensor,
    torch.as_tensor,
    torch.scalar_tensor,
    torch.empty_strided,
}


class _StrayMaker(TorchFunctionMode):
    def __init__(self):
        super().__init__()
        self.strays: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        caller = sys._getframe(1).f_code.co_filename
        if "/torch/" in caller or _is_reader(caller):  # torch's own code (nn layers' parameters), or reading data
            return func(*args, **kwargs)
        if func is torch.from_numpy:
            self._record()
            return func(*args, **kwargs).to("meta")
        if (
            func in FACTORIES
            and kwargs.get("device") is None
            and kwargs.get("generator") is None
            and not _keeps_device(func, args)
        ):
            self._record()
            kwargs["device"] = "meta"
        return func(*args, **kwargs)

    def _record(self) -> None:
        ours = [f for f in traceback.extract_stack()[:-2] if "/matspray/" in f.filename and "/tests/" not in f.filename]
        if ours:
            frame = ours[-1]
            self.strays.append(f"{frame.filename.split('/matspray/', 1)[-1]}:{frame.lineno}: {frame.line}")


def _is_reader(filename: str) -> bool:
    return "/matspray/data/" in filename and not filename.endswith("/camera.py")


def _keeps_device(func, args) -> bool:  # as_tensor / tensor of a tensor keep (or copy on) its device
    return func in (torch.as_tensor, torch.tensor) and bool(args) and isinstance(args[0], torch.Tensor)


@contextmanager
def stray_tensor_check():
    """Yields the list of 'file:line: code' where our code made a tensor on the default device."""
    maker = _StrayMaker()
    with maker:
        yield maker.strays
