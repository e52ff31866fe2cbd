"""Which rasterizer renders: `torch` (ours, CPU and CUDA) or `gsplat` (CUDA only, an optional extra).

`resolve_backend` turns the setting `backend` (auto | torch | gsplat) into the one that runs, once per
run; a request that cannot be met is a SettingError that says what is missing and how to get it.
"""

from __future__ import annotations

import importlib

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
