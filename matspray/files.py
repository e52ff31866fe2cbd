"""File helpers that need no torch, so that a run folder can be checked before torch is imported (`matspray view`
opens its page first; see view/launch.py)."""

from __future__ import annotations

import os
from pathlib import Path

HDR_SUFFIXES = (".exr", ".hdr")  # the high-dynamic-range image files MatSpray reads as lights


def atomic_target(path: Path) -> Path:
    """A temporary sibling of `path` to write into before `os.replace` (same folder, same suffix)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
