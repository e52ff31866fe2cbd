"""Each optional package, missing, is one line naming the extra that installs it, never an ImportError traceback:
the code that needs it runs in a process where it does not import (as where its extra is not installed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.test_cli import run_cli_without

# (module, extra, Python code that needs it)
LIBRARY_USES = [
    ("cv2", "captures", "from matspray.data.undistort import opencv; opencv()"),
    (
        "imageio_ffmpeg",
        "video",
        "import torch; from matspray.data.formats.video import write_video; "
        "write_video([torch.zeros(4, 4, 3)], 'x.mp4', 24)",
    ),
    ("mitsuba", "synth", "from matspray.synth.mitsuba_scene import select_variant; select_variant()"),
    ("viser", "view", "from matspray.view.launch import open_page; open_page('127.0.0.1', 0)"),
    (
        "diffusers",
        "marigold",
        "from matspray.predictors.marigold import _load; _load('none', 'MarigoldIntrinsicsPipeline', 'model', '')",
    ),
    ("pycolmap", "colmap", "from matspray.data.formats.colmap import read_colmap; read_colmap('none')"),
]


def said_without(module: str, code: str, cwd) -> subprocess.CompletedProcess:
    program = (
        f"import sys; sys.modules[{module!r}] = None\n"
        "from matspray.errors import MatsprayError\n"
        f"try:\n    {code}\nexcept MatsprayError as error:\n    print(error, file=sys.stderr); sys.exit(2)\n"
    )
    return subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120, cwd=cwd)


@pytest.mark.parametrize("module, extra, code", LIBRARY_USES, ids=[m for m, _, _ in LIBRARY_USES])
def test_a_missing_optional_package_names_its_extra(module, extra, code, tmp_path):
    result = said_without(module, code, tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and f"pip install 'matspray[{extra}]'" in lines[0], lines
    assert not list(tmp_path.iterdir())  # nothing half-written


@pytest.mark.parametrize("module", ["trimesh", "xatlas", "skimage", "fast_simplification", "scipy", "pygltflib"])
def test_export_without_its_extra_says_so_before_reading_anything(module, tmp_path):
    result = run_cli_without(module, "export", "--run", tmp_path / "no-run", "--out", tmp_path / "x.glb")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and f"matspray export needs {module}" in lines[0], lines
    assert "pip install 'matspray[export]'" in lines[0] and not list(tmp_path.iterdir())
