"""Which rasterizer renders: `torch` (ours, CPU and CUDA) or `gsplat` (CUDA only, an optional extra).

`resolve_backend` turns the setting `backend` (auto | torch | gsplat) into the one that runs, once per
run; a request that cannot be met is a SettingError that says what is missing and how to get it.

One run renders with one backend. Rather than add a `backend` argument to every function between a stage and
`rasterize` (relighting, G-buffers, masks, evaluation, export all reach it through layers that have nothing
to do with the choice), a stage runs inside `rendering_with(backend)`, and `rasterize` called without an
explicit backend takes that one. The `RenderUse` it yields counts what each call really ran on, which is
what a stage's record and the benchmarks report (not what was asked for).
"""

from __future__ import annotations

import importlib
from collections import Counter
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

import torch

from matspray.errors import SettingError

BACKENDS = ("auto", "torch", "gsplat")
INSTALL_HINT = "pip install 'matspray[cuda]' (needs nvcc and ninja; the first import compiles CUDA code)"


def gsplat_import_error() -> str | None:
    """None when `import gsplat` works, else why it does not (one line)."""
    try:
        importlib.import_module("gsplat")
    except Exception as exc:  # ImportError, or a failed CUDA build at import time
        return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": ")
    return None


def resolve_backend(name: str, device) -> str:
    """'torch' or 'gsplat' for the setting `name` on `device` (a torch.device or its string)."""
    if name not in BACKENDS:
        raise SettingError("backend", f"unknown backend '{name}'; choose one of {', '.join(BACKENDS)}")
    if name == "torch":
        return "torch"
    on_cuda = torch.device(device).type == "cuda" and torch.cuda.is_available()
    if name == "auto":
        return "gsplat" if on_cuda and gsplat_import_error() is None else "torch"
    if not on_cuda:
        raise SettingError("backend", f"gsplat needs a CUDA device and there is none here (device {device}); use --backend torch")
    error = gsplat_import_error()
    if error is not None:
        raise SettingError("backend", f"gsplat is not installed or does not import ({error}); {INSTALL_HINT}")
    return "gsplat"


@dataclass
class RenderUse:
    """The backend a block of work renders with, and what it really ran: {"torch" | "gsplat" | "rays": calls}."""
    backend: str
    calls: Counter = field(default_factory=Counter)

    def used(self) -> dict[str, int]:
        return dict(sorted(self.calls.items()))


_ACTIVE: ContextVar[RenderUse | None] = ContextVar("matspray_render_use", default=None)


@contextmanager
def rendering_with(backend: str):
    """Within the block, `rasterize(..., backend=None)` renders with `backend` ('torch' or 'gsplat', already
    resolved); yields the block's RenderUse. Blocks nest; each call is counted in the innermost one."""
    if backend not in ("torch", "gsplat"):
        raise ValueError(f"rendering_with: a resolved backend (torch or gsplat), got {backend!r}")
    use = RenderUse(backend)
    token = _ACTIVE.set(use)
    try:
        yield use
    finally:
        _ACTIVE.reset(token)


def active_backend() -> str:
    """The backend of the innermost `rendering_with` block; torch outside any."""
    use = _ACTIVE.get()
    return "torch" if use is None else use.backend


def note_render(kind: str) -> None:
    """Count one call of a renderer ('torch', 'gsplat', or 'rays' for the lifting ray tracer) in the active block."""
    use = _ACTIVE.get()
    if use is not None:
        use.calls[kind] += 1
