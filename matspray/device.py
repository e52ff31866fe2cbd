"""Which torch device a command runs on."""

import torch

from matspray.errors import ConfigError


def resolve_device(name: str) -> torch.device:
    """`auto` (CUDA when available, else CPU), `cpu`, `cuda` or `cuda:N`, with a clear error otherwise."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"--device: unknown device '{name}'; use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {name}: this torch build or machine has no CUDA; use --device cpu")
    return device


def configure_threads(device: torch.device | None = None) -> int:
    """Use one CPU thread unless $MATSPRAY_THREADS says otherwise. This code runs many small tensor
    ops (per-hit gathers, scatters, sorts); on a 2-core machine a second thread makes them 2-3x slower
    (measured: one lifting view at 4x4 rays, 2.0 s with one thread, 5.5 s with two)."""
    import os

    if device is not None and device.type == "cuda":
        return torch.get_num_threads()
    value = os.environ.get("MATSPRAY_THREADS", "1")
    try:
        threads = int(value)
    except ValueError:
        raise ConfigError(f"$MATSPRAY_THREADS must be a positive integer, got '{value}'") from None
    if threads < 1:
        raise ConfigError(f"$MATSPRAY_THREADS must be >= 1, got {threads}")
    torch.set_num_threads(threads)
    return threads
