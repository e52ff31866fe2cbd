"""$MATSPRAY_THREADS holds for the test suite as for a run (conftest applies it)."""

import os
import subprocess
import sys

from tests.conftest import ROOT


def test_matspray_threads_reaches_the_tests(tmp_path):
    test = tmp_path / "test_threads_seen.py"
    test.write_text("import torch\n\n\ndef test_one():\n    assert torch.get_num_threads() == 1\n")
    env = {**os.environ, "MATSPRAY_THREADS": "1"}
    args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest", str(test)]
    done = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
