"""`benchmarks.mitsuba_reduced`: Mitsuba cut down to the variants and plugins `matspray synth` renders the demo object
with still renders it, the same images as the whole package, and packs into an archive well within the GPU machine's
64 MiB carry limit."""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

from benchmarks.mitsuba_reduced import build, kept, probe
from matspray.data.images import read_raw
from matspray.synth.mitsuba_scene import _PROBE

pytest.importorskip("mitsuba", reason="Mitsuba is not installed (pip install 'matspray[synth]')")
ROOT = Path(__file__).resolve().parents[1]
CARRY_LIMIT = 64 * 2**20


def test_the_variants_and_plugins_kept():
    variants, plugins = ("scalar_rgb",), ["path.so"]
    assert kept("mitsuba/scalar_rgb.cpython-311-x86_64-linux-gnu.so", variants, plugins)
    assert not kept("mitsuba/llvm_ad_rgb.cpython-311-x86_64-linux-gnu.so", variants, plugins)
    assert kept("mitsuba/mitsuba_ext.cpython-311-x86_64-linux-gnu.so", variants, plugins)
    assert kept("mitsuba/plugins/path.so", variants, plugins)
    assert not kept("mitsuba/plugins/volpath.so", variants, plugins)
    assert kept("mitsuba/libembree3.so", variants, plugins) and kept("drjit/__init__.py", variants, plugins)
    assert not kept("mitsuba/include/mitsuba/core/vector.h", variants, plugins)
    assert not kept("mitsuba-3.9.1.dist-info/RECORD", variants, plugins)


@pytest.mark.slow
def test_the_reduced_package_renders_what_the_whole_one_does(tmp_path):
    archive = tmp_path / "mitsuba.tar.xz"
    figures = build(archive, ("scalar_rgb",), tmp_path / "whole", level=0)
    assert archive.stat().st_size < CARRY_LIMIT / 2, figures
    unpacked = tmp_path / "reduced"
    with tarfile.open(archive) as opened:
        opened.extractall(unpacked, filter="data")
    environment = {**os.environ, "PYTHONPATH": f"{unpacked}{os.pathsep}{ROOT}"}
    found = probe(tmp_path / "by-reduced", environment=environment)
    assert found["mitsuba"].startswith(str(unpacked)) and found["plugins"] == figures["plugins"]
    assert {"stratified.so", "independent.so", "sphere.so", "constant.so"} <= set(found["plugins"])
    # the scene `select_variant` checks a variant with renders there too
    check = subprocess.run([sys.executable, "-c", _PROBE.format(variant="scalar_rgb")], env=environment)
    assert check.returncode == 0
    for split in ("train", "test"):
        whole = sorted((tmp_path / "whole" / split).rglob("*.png"))
        assert whole
        for path in whole:
            other = tmp_path / "by-reduced" / path.relative_to(tmp_path / "whole")
            assert np.array_equal(read_raw(path).numpy(), read_raw(other).numpy()), path
