"""benchmarks.training_parts runs and prints a figure per part it was asked for."""

from __future__ import annotations

import sys

import torch

from benchmarks import training_parts


def test_it_times_each_part(monkeypatch, capsys):
    threads = str(torch.get_num_threads())  # the process's own count: the benchmark sets it
    argv = ["training_parts", "--sizes", "24", "--gaussians", "300", "--repeats", "2", "--threads", threads]
    monkeypatch.setattr(sys, "argv", argv)
    training_parts.main()
    out = capsys.readouterr().out
    assert "D-SSIM loss, 24x24 px, forward+backward:" in out
    assert "SH colour (numba, degree 3), 300 Gaussians, forward+backward:" in out
    assert "oriented normals (torch), 300 Gaussians" in out and "oriented normals (numba), 300 Gaussians" in out
    assert "compiled from an empty cache" not in out  # only with --compile
