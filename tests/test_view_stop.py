"""`matspray view` stopped by Ctrl+C right after it is ready (its warm-up render and photo loading still running in
their threads) exits cleanly: status 0, "stopped", no abort from a thread left inside torch or numba."""

import signal
import socket
import subprocess
import sys
import urllib.request

import pytest

from tests.test_view import make_view_run


def test_ctrl_c_right_after_ready_exits_cleanly(tmp_path):
    pytest.importorskip("viser", reason="matspray view needs viser (pip install 'matspray[view]')")
    run = make_view_run(tmp_path, gaussians=200)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    command = [sys.executable, "-m", "matspray", "view", "--run", str(run), "--port", str(port), "--device", "cpu"]
    viewer = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        while not lines or "matspray view: ready" not in lines[-1]:
            line = viewer.stdout.readline()
            assert line, "".join(lines) + viewer.stderr.read()
            lines.append(line)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
            assert page.status == 200
        viewer.send_signal(signal.SIGINT)
        # stopping waits for the warm-up's threads (up to a minute each where numba is still compiling a kernel)
        out, err = viewer.communicate(timeout=300)
    finally:
        if viewer.poll() is None:
            viewer.kill()
            viewer.communicate()
    assert viewer.returncode == 0, err
    assert out.strip().endswith("matspray view: stopped") and "terminate called" not in err and "Traceback" not in err
