"""The peak resident memory of a block (matspray.memory) and the stage records that keep it."""

import numpy as np
import pytest

from matspray.memory import CLEAR_REFS, memory_line, peak_memory, peak_rss_bytes, process_peak_bytes
from matspray.rundir import RunDir, read_json, timed

MIB = 2**20


def _can_reset() -> bool:
    try:
        CLEAR_REFS.write_text("5")
        return peak_rss_bytes() is not None
    except OSError:
        return False


needs_proc = pytest.mark.skipif(not _can_reset(), reason="no /proc/self/clear_refs (not Linux): peaks are not measured")


def _touch(megabytes: int) -> np.ndarray:
    return np.ones(megabytes * MIB, dtype=np.uint8)  # every page written: resident


@needs_proc
def test_a_block_sees_its_own_peak_and_not_an_earlier_one():
    with peak_memory() as big:
        block = _touch(300)
        del block
    with peak_memory() as small:
        _touch(10)
    start = peak_rss_bytes()
    assert big.bytes >= 300 * MIB
    # the second block starts after the 300 MiB went back: its peak is its own, not the process's
    assert small.bytes < big.bytes - 200 * MIB, (small.mib, big.mib, start / MIB)
    assert process_peak_bytes() >= big.bytes  # the whole process still knows its peak through the resets


@needs_proc
def test_an_enclosing_block_keeps_the_peak_of_a_block_inside_it():
    with peak_memory() as outer:
        first = _touch(250)  # before the inner block resets the peak
        del first
        with peak_memory() as inner:
            _touch(20)
        after = _touch(5)
        del after
    assert outer.bytes >= 250 * MIB
    assert inner.bytes < outer.bytes - 150 * MIB


def test_a_finished_stage_records_its_peak_and_run_prints_it(tmp_path):
    run = RunDir(tmp_path / "run")
    with timed() as timer:
        _touch(50)
    run.finish_stage("geometry", "fp", {}, timer.seconds, {"note": 1}, timer.peak_mib)
    run.finish_stage("lift", "fp", {}, 1.0, None, 1536.0)
    run.finish_stage("masks", "fp", {}, 1.0)  # no peak known: none recorded
    record = read_json(run.path("geometry", "stage.json"))
    if timer.peak_mib is None:
        assert "peak_memory_mib" not in record
    else:
        assert record["peak_memory_mib"] == timer.peak_mib >= 50
    assert "peak_memory_mib" not in read_json(run.path("masks", "stage.json"))
    peaks = run.peak_memory()
    assert peaks["lift"] == 1536.0 and "masks" not in peaks
    line = memory_line({"lift": 1536.0}, 3 * 2**30)
    assert line == "peak memory: 3.00 GB; GB per stage: lift 1.50"
    assert memory_line({}, None) == "peak memory: unknown"


@needs_proc
def test_memory_freed_in_small_blocks_leaves_the_process_when_a_stage_ends():
    """glibc keeps freed small blocks (below its mmap threshold) in its heap; the end of a stage (`timed`) hands them
    back, so the next stage does not start on top of the last one's peak."""
    import psutil

    process = psutil.Process()
    start = process.memory_info().rss
    with timed():
        blocks = [bytes(2000) + bytes([i % 256]) for i in range(100_000)]  # 200 MB of heap blocks
        top = blocks[-1:]  # the heap's top stays in use: free() alone cannot shrink the heap
        del blocks
        held = process.memory_info().rss
    after = process.memory_info().rss
    assert held - start > 150 * MIB  # freed, but still resident before the stage ended
    assert after - start < 50 * MIB, ((held - start) / MIB, (after - start) / MIB)
    assert top
