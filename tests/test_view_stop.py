"""`matspray view` stopped by Ctrl+C right after it is ready (its warm-up render and photo loading still running in
their threads) exits cleanly: status 0, "stopped", no abort from a thread left inside torch or numba."""

import sys

import pytest

from tests.test_view import make_view_run
from tests.viewer_process import free_port, serve_then_interrupt


def test_ctrl_c_right_after_ready_exits_cleanly(tmp_path):
    pytest.importorskip("viser", reason="matspray view needs viser (pip install 'matspray[view]')")
    run = make_view_run(tmp_path, gaussians=200)
    port = free_port()
    command = [sys.executable, "-m", "matspray", "view", "--run", str(run), "--port", str(port), "--device", "cpu"]
    # stopping waits for the warm-up's threads (up to a minute each where numba is still compiling a kernel)
    stopped = serve_then_interrupt(command, port, stop_timeout=300)
    assert stopped.page_status == 200
    assert stopped.returncode == 0, stopped.err
    out, err = stopped.out, stopped.err
    assert out.strip().endswith("matspray view: stopped") and "terminate called" not in err and "Traceback" not in err
