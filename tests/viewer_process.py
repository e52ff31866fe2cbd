"""`matspray view` as a user runs it, in its own process: a free port, and one serve-then-Ctrl+C cycle for the tests
that check it starts, serves its page and stops cleanly."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
from dataclasses import dataclass

READY = "matspray view: ready"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class ViewerExit:
    returncode: int
    lines: list[str]  # stdout up to and including the ready line
    page_status: int
    page: bytes  # the page served at /
    out: str  # stdout after the ready line
    err: str


def interruptible() -> None:
    """In the viewer's process before it starts: Ctrl+C as a terminal gives it. A test run started in the background
    of a non-interactive shell (`bash .ci/run &`) has SIGINT ignored, which the viewer would inherit; Python then
    installs no KeyboardInterrupt handler, and Ctrl+C never stops it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def serve_then_interrupt(command: list[str], port: int, stop_timeout: float, cwd=None, env=None) -> ViewerExit:
    """Start the viewer `command` (listening on `port`), wait for its ready line, fetch its page, send Ctrl+C and wait
    up to `stop_timeout` s for it to exit; a viewer that is still running then is aborted and the test fails with
    its threads' stacks."""
    import urllib.request

    env = {**(os.environ if env is None else env), "PYTHONFAULTHANDLER": "1"}
    viewer = subprocess.Popen(
        command,
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=interruptible,
    )
    lines: list[str] = []
    try:
        while not lines or READY not in lines[-1]:
            line = viewer.stdout.readline()
            assert line, "".join(lines) + viewer.stderr.read()  # it ended before it was ready
            lines.append(line)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
            status, body = page.status, page.read()
        viewer.send_signal(signal.SIGINT)
        try:
            out, err = viewer.communicate(timeout=stop_timeout)
        except subprocess.TimeoutExpired:
            # a viewer that does not stop: SIGABRT makes faulthandler (PYTHONFAULTHANDLER) print where every
            # thread is, so that the failure says what it was waiting for
            viewer.send_signal(signal.SIGABRT)
            out, err = viewer.communicate(timeout=60)
            raise AssertionError(
                f"the viewer did not stop within {stop_timeout} s of Ctrl+C; its threads:\n{err[-6000:]}"
            )
    finally:
        if viewer.poll() is None:
            viewer.kill()
            viewer.communicate()
    return ViewerExit(viewer.returncode, lines, status, body, out, err)
