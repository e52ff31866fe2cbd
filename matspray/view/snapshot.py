"""The snapshot button: the picture shown, at full size, as a PNG in RUN/view/ (written atomically: a reader never
sees half a file, and an interrupted write leaves none)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import numpy as np
import torch

from matspray.data.images import atomic_target, write_raw

FOLDER = "view"


def snapshot_name(variant: str, light: str, mode: str, stamp: float | None = None) -> str:
    """'<variant>_<light>_<mode>_<YYYYmmdd-HHMMSS>.png' with file-name-safe parts."""
    when = time.strftime("%Y%m%d-%H%M%S", time.localtime(time.time() if stamp is None else stamp))
    parts = [re.sub(r"[^a-z0-9]+", "-", part.lower()).strip("-") or "x" for part in (variant, light, mode)]
    return "_".join(parts + [when]) + ".png"


def write_snapshot(
    run_root, image: np.ndarray, variant: str, light: str, mode: str, stamp: float | None = None
) -> Path:
    """Write `image` ([H, W, 3] uint8, as shown) to RUN/view/; a name already taken gets
    -2, -3, ... Returns the path."""
    folder = Path(run_root) / FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    name = snapshot_name(variant, light, mode, stamp)
    path, k = folder / name, 2
    while path.exists():
        path, k = folder / name.replace(".png", f"-{k}.png"), k + 1
    try:
        write_raw(
            path, torch.from_numpy(np.ascontiguousarray(image)).float() / 255.0
        )  # exact: k / 255 rounds back to k
    finally:
        leftover = atomic_target(path)  # written into first and renamed; only a failed write leaves it behind
        if leftover.exists():
            leftover.unlink()
    return path
