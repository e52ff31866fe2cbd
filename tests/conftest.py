"""Fixtures shared by test modules."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOLDER = "import sys, time\nfrom matspray.rundir import RunDir\nheld = RunDir(sys.argv[1]).hold()\nprint('held', flush=True)\ntime.sleep(120)\n"


def busy_message(run, pid) -> str:
    """What a writer is told about a run folder that process `pid` holds."""
    return f"{run}: another MatSpray process (pid {pid}) is writing this run folder; wait for it to finish, or use another run folder"


@pytest.fixture
def hold_in_another_process():
    """hold(run) -> a process (Popen) that holds `run`'s run lock until the test ends or it is killed."""
    started = []

    def hold(run: Path) -> subprocess.Popen:
        process = subprocess.Popen([sys.executable, "-c", HOLDER, str(run)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
        started.append(process)
        assert process.stdout.readline().strip() == "held"
        return process

    yield hold
    for process in started:
        process.kill()
        process.wait()
