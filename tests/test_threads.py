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


def test_torchs_openmp_threads_spin_briefly_unless_the_user_says_otherwise():
    """matspray sets libgomp's spin before torch is imported (matspray/__init__.py), where torch's OpenMP reads it;
    a value in the environment stays."""
    code = (
        "import os, matspray.cli, torch\n"
        "assert 'OpenMP' in torch.__config__.parallel_info()  # the threads the setting is for\n"
        "print(os.environ['GOMP_SPINCOUNT'])"
    )
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    for given, expected in ((None, "10000"), ("300000", "300000")):
        run_env = env if given is None else {**env, "GOMP_SPINCOUNT": given}
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=run_env)
        assert done.returncode == 0, done.stderr[-2000:]
        assert done.stdout.strip() == expected
