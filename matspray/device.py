"""Which torch device a command runs on."""

import torch

from matspray.errors import ConfigError, SettingError


def resolve_device(name: str) -> torch.device:
    """`auto` (CUDA when available, else CPU), `cpu`, `cuda` or `cuda:N`, with a clear error otherwise."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise SettingError("device", f"unknown device '{name}'; use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SettingError("device", f"{name}: this torch build or machine has no CUDA; use cpu")
    return device


def configure_threads(device: torch.device | None = None) -> int:
    """Torch's CPU threads: $MATSPRAY_THREADS when set, else torch's default (one per core).
    Measured on an idle 2-core machine, two threads against one: 400 geometry steps 71 s vs 107 s,
    one lifting view at 4x4 rays 1.0 s vs 1.5 s, 40 refinement steps 16 s vs 24 s. (Under a second
    CPU-bound process two threads fight over the cores; set MATSPRAY_THREADS=1 then.)"""
    import os

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
