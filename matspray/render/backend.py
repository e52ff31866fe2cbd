"""Which rasterizer renders: `torch` (ours, CPU and CUDA: the readable reference), `numba` (ours, compiled tile
loops, CPU only; matspray.render.numba.backend) or `gsplat` (CUDA only, an optional extra).

`resolve_backend` turns the setting `backend` (auto | torch | numba | gsplat) into the one that runs; a request
that cannot be met is a SettingError of one line that says what is missing and how to get it. `auto` is gsplat
on a CUDA device that can run it, else torch there (saying why in one line, once per process), and numba on
the CPU (torch, silently, if numba does not import: it is a core dependency, so only a broken install).

gsplat (1.5) compiles its CUDA code at its first kernel call, not at import: `import gsplat` working says
nothing about the build. So the first check on a CUDA device (`gsplat_device_error`, cached per process and
device) loads the extension through `gsplat.cuda._backend`, renders one Gaussian with it, and says how long
that took (minutes when it compiles, seconds from the build cache).

One run renders with one backend. Rather than add a `backend` argument to every function between a stage and
`rasterize` (relighting, G-buffers, masks, evaluation, export all reach it through layers that have nothing
to do with the choice), a stage runs inside `rendering_with(backend)`, and `rasterize` called without an
explicit backend takes that one. The `RenderUse` it yields counts what each call really ran on, which is
what a stage's record and the benchmarks report (not what was asked for).
"""

from __future__ import annotations

import importlib
import sys
from collections import Counter
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from time import perf_counter
from typing import Callable

import torch

from matspray.device import configure_threads, resolve_device
from matspray.errors import SettingError

BACKENDS = ("auto", "torch", "numba", "gsplat")
INSTALL_HINT = "pip install 'matspray[cuda]' (needs nvcc and ninja; the first use compiles CUDA code)"
BUILD_HINT = (
    "gsplat compiles its CUDA code with nvcc and ninja: install the CUDA toolkit of torch's CUDA version "
    "and `pip install ninja`, or use backend torch"
)

Notify = Callable[[str], None]
# per process (one CUDA extension per process, whichever GPU): why gsplat cannot render on CUDA (None: it can),
# and whether `auto` has said so
_CHECKED: dict[str, str | None] = {}
_TOLD: set[str] = set()


def _to_stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def gsplat_import_error() -> str | None:
    """None when `import gsplat` works, else why it does not (one line)."""
    try:
        importlib.import_module("gsplat")
    except Exception as exc:  # ImportError, or anything gsplat's own imports raise
        return _one_line(exc)
    return None


def gsplat_cuda_error(device, notify: Notify | None = None) -> str | None:
    """None when gsplat's CUDA extension loads and renders one Gaussian on `device`, else why not (one line).
    Loading compiles the extension the first time (minutes); `notify` (default: stderr) hears how long it took."""
    start = perf_counter()
    try:
        extension = importlib.import_module("gsplat.cuda._backend")  # compiles here, or loads the cached build
        if getattr(extension, "_C", None) is None:  # gsplat found no nvcc and printed so; it raises nothing
            return "gsplat found no CUDA toolkit (nvcc) to compile its CUDA code with"
        alpha = _render_one_gaussian(torch.device(device))
    except Exception as exc:  # a failed build (RuntimeError from ninja), a missing symbol, no kernel for this GPU...
        return _one_line(exc)
    if not 0.45 < alpha <= 0.5:  # opacity 0.5, 4 px wide, centred on a pixel corner: 0.492 at the four centre pixels
        return f"gsplat's CUDA extension rendered a test Gaussian wrongly (alpha {alpha:.3f} where 0.5 was drawn)"
    (notify or _to_stderr)(
        f"gsplat: CUDA extension ready in {perf_counter() - start:.1f} s "
        "(compiled at its first use, reused from the build cache after that)"
    )
    return None


def _render_one_gaussian(device: torch.device) -> float:
    """The largest alpha of one Gaussian (opacity 0.5, 4 px sigma) rendered by gsplat at the centre of a
    16 x 16 image."""
    gsplat = importlib.import_module("gsplat")
    with torch.no_grad():
        _, alphas, _ = gsplat.rasterization(
            torch.tensor([[0.0, 0.0, 2.0]], device=device),
            torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device),
            torch.full((1, 3), 0.5, device=device),
            torch.tensor([0.5], device=device),
            torch.ones(1, 3, device=device),
            torch.eye(4, device=device)[None],
            torch.tensor([[[16.0, 0.0, 8.0], [0.0, 16.0, 8.0], [0.0, 0.0, 1.0]]], device=device),
            16,
            16,
            packed=False,
        )
    return float(alphas.max())  # a float: waits for the kernels, so that their errors surface here


def gsplat_device_error(device, notify: Notify | None = None) -> str | None:
    """None when backend gsplat can render on `device`, else why not and how to get it (one line). Cached per
    process. (tests/gsplat_cpu.py replaces this function to run gsplat's Python code on the CPU.)"""
    device = torch.device(device)
    if device.type != "cuda" or not torch.cuda.is_available():
        return f"gsplat needs a CUDA device and there is none here (device {device}); use backend torch"
    key = device.type
    if key not in _CHECKED:
        error = gsplat_import_error()
        if error is not None:
            _CHECKED[key] = f"gsplat is not installed or does not import ({error}); {INSTALL_HINT}"
        else:
            error = gsplat_cuda_error(device, notify)
            _CHECKED[key] = (
                None if error is None else f"gsplat's CUDA extension does not build or run ({error}); {BUILD_HINT}"
            )
    return _CHECKED[key]


def numba_device_error(device) -> str | None:
    """None when backend numba can render on `device`, else why not and what to use instead (one line)."""
    if torch.device(device).type != "cpu":
        return f"numba renders on the CPU only (device {device}); use backend torch or gsplat there, or device cpu"
    try:
        importlib.import_module("numba")
    except Exception as exc:  # numba is a core dependency: only a broken install gets here
        return (
            f"numba does not import ({_one_line(exc)}); reinstall matspray (pip install matspray) or use backend torch"
        )
    return None


def resolve_backend(name: str, device, notify: Notify | None = None) -> str:
    """'torch', 'numba' or 'gsplat' for the setting `name` on `device` (a torch.device or its string). `notify`
    (default: stderr) hears, once per process, how long gsplat's CUDA extension took to load and why `auto`
    renders with torch on a CUDA device."""
    if name not in BACKENDS:
        raise SettingError("backend", f"unknown backend '{name}'; choose one of {', '.join(BACKENDS)}")
    if name == "torch":
        return "torch"
    if name == "numba":
        error = numba_device_error(device)
        if error is not None:
            raise SettingError("backend", error)
        return "numba"
    error = gsplat_device_error(device, notify)
    if error is None:
        return "gsplat"
    if name == "gsplat":
        raise SettingError("backend", error)
    key = torch.device(device).type
    if key != "cuda":  # auto on the CPU: the compiled rasterizer, without a word
        return "numba" if numba_device_error(device) is None else "torch"
    if key not in _TOLD:
        _TOLD.add(key)
        (notify or _to_stderr)(f"backend auto: rendering with torch; {error}")
    return "torch"


@dataclass
class RenderUse:
    """The backend a block of work renders with, and what it really ran:
    {"torch" | "numba" | "gsplat" | "rays" | "rays-numba": calls}."""

    backend: str
    calls: Counter = field(default_factory=Counter)
    outer: "RenderUse | None" = None  # the enclosing block, which counts this block's calls too

    def used(self) -> dict[str, int]:
        return dict(sorted(self.calls.items()))


_ACTIVE: ContextVar[RenderUse | None] = ContextVar("matspray_render_use", default=None)


@contextmanager
def rendering_with(backend: str):
    """Within the block, `rasterize(..., backend=None)` renders with `backend` ('torch', 'numba' or 'gsplat',
    already resolved); yields the block's RenderUse. Blocks nest: the innermost decides the backend, and each call
    is counted in it and in every block around it."""
    if backend not in ("torch", "numba", "gsplat"):
        raise ValueError(f"rendering_with: a resolved backend (torch, numba or gsplat), got {backend!r}")
    use = RenderUse(backend, outer=_ACTIVE.get())
    token = _ACTIVE.set(use)
    try:
        yield use
    finally:
        _ACTIVE.reset(token)


def active_backend() -> str:
    """The backend of the innermost `rendering_with` block; torch outside any."""
    use = _ACTIVE.get()
    return "torch" if use is None else use.backend


def compiled_on_cpu(device) -> bool:
    """Whether per-Gaussian work on `device` (SH colour, normals) runs in backend numba's compiled loops: inside a
    block that renders with numba, on the CPU."""
    return active_backend() == "numba" and torch.device(device).type == "cpu"


def note_render(kind: str) -> None:
    """Count one call of a renderer ('torch', 'numba', 'gsplat', or 'rays' / 'rays-numba' for lifting's torch /
    compiled ray tracer) in the active block."""
    use = _ACTIVE.get()
    while use is not None:
        use.calls[kind] += 1
        use = use.outer


def compute_target(device: str = "auto", backend: str = "auto", notify=None) -> tuple[torch.device, str]:
    """The device and rasterizer a command computes with (--device, --backend), checked before any work, and the
    CPU threads set for it. `notify` hears gsplat's build time and why `auto` falls back (default: stderr)."""
    resolved = resolve_device(device)
    configure_threads(resolved)
    return resolved, resolve_backend(backend, resolved, notify=notify)
