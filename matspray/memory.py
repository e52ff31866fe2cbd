"""The peak resident memory of a block of code (a stage), for the run's records.

Linux keeps a process's peak resident set (VmHWM in /proc/self/status) and lets the process reset it to the current
resident set (writing 5 to /proc/self/clear_refs), so a stage's own peak is measured without sampling: reset at its
start, read at its end. Blocks may nest: a reset inside one first folds the peak so far into every enclosing block.
Where /proc is absent or refuses the reset (not Linux), the peak is None and nothing is recorded.

`release_free_memory()` hands what the C allocator holds free back to the system (glibc's malloc_trim): glibc keeps
freed small blocks in its arenas (one per thread that allocated: pycolmap's SIFT threads, torch's), so without it a
stage's peak stays resident after the stage and the next stage's peak comes on top of it."""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from contextlib import contextmanager
from pathlib import Path

STATUS, CLEAR_REFS = Path("/proc/self/status"), Path("/proc/self/clear_refs")
_open: list["Peak"] = []  # the blocks being measured, outermost first
_lock = threading.Lock()
_forgotten = [0]  # the highest peak a reset has forgotten (see process_peak_bytes)


def peak_rss_bytes() -> int | None:
    """The process's peak resident memory since it started or since the last reset (VmHWM); None when unknown."""
    try:
        for line in STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024  # "VmHWM:   123456 kB"
    except (OSError, ValueError, IndexError):
        pass
    return None


def _libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC = _libc()


def release_free_memory() -> bool:
    """Give the allocator's free memory back to the system (glibc; elsewhere nothing happens). Returns whether it
    could: the memory in use is untouched, only pages no block uses are released."""
    if _LIBC is None:
        return False
    _LIBC.malloc_trim(0)
    return True


def process_peak_bytes() -> int | None:
    """The process's peak resident memory since it started, through the resets of `peak_memory`; None when unknown."""
    now = peak_rss_bytes()
    return None if now is None else max(now, _forgotten[0])


def _reset_peak() -> bool:
    try:
        CLEAR_REFS.write_text("5")
        return True
    except OSError:
        return False


class Peak:
    """`bytes`: the peak resident memory of the process during the block (after it ends); None when unknown."""

    def __init__(self):
        self.bytes: int | None = None

    def fold(self, value: int | None) -> None:
        if value is not None and self.bytes is not None:
            self.bytes = max(self.bytes, value)

    @property
    def mib(self) -> float | None:
        return None if self.bytes is None else round(self.bytes / 2**20, 1)


@contextmanager
def peak_memory():
    """`with peak_memory() as peak: ...; peak.bytes`: the peak resident memory of the whole process during the block
    (every thread's allocations, the memory it held when it started included)."""
    peak = Peak()
    with _lock:
        before = peak_rss_bytes()
        for outer in _open:  # the reset below forgets the peak so far: the enclosing blocks keep it
            outer.fold(before)
        _forgotten[0] = max(_forgotten[0], before or 0)
        if before is not None and _reset_peak():
            peak.bytes = 0
        _open.append(peak)
    try:
        yield peak
    finally:
        with _lock:
            _open.remove(peak)
            now = peak_rss_bytes()
            peak.fold(now)
            for outer in _open:
                outer.fold(now)


def memory_line(stages: dict, process_bytes: int | None) -> str:
    """One line for the end of a run: each stage's peak resident memory ({stage: MiB}, `RunDir.peak_memory`) and the
    process's (bytes)."""
    whole = "unknown" if process_bytes is None else f"{process_bytes / 2**30:.2f} GB"
    each = ", ".join(f"{stage} {mib / 1024:.2f}" for stage, mib in stages.items())
    return f"peak memory: {whole}" + (f"; GB per stage: {each}" if each else "")
