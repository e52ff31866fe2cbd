"""benchmarks/merger_batches.py: each batch's share of the merger's weight against equal weights."""

from __future__ import annotations

import pytest
import torch

from benchmarks.merger_batches import batch_shares, main, pooled


def batch(views, metal):
    return {"views": views, "exposure": 1.0, "shading": 0.5, "roughness_offset": 0.0, "spurious_metallic": metal}


def test_shares_are_ratios_to_equal_weights_over_the_seen_views_and_pool_by_metallic():
    views = ["a", "b", "c", "d"]
    seen = torch.tensor([[True, True, True, True], [True, True, False, False]])
    # Gaussian 0: all weight on view a; Gaussian 1 (seen by a and b only): equal weights
    w = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]])
    weights = {"base_color": w, "roughness": seen.float() / seen.sum(1, keepdim=True), "metallic": w}
    rows = batch_shares(weights, seen, views, [batch(["a", "b"], 0.3), batch(["c", "d"], 0.0)])
    # equal weights put (0.5 + 1.0) / 2 = 0.75 on batch 0 and 0.25 on batch 1; the merger puts 1.0 and 0.0
    assert rows[0]["uniform"] == pytest.approx(0.75) and rows[1]["uniform"] == pytest.approx(0.25)
    assert rows[0]["ratio"]["base_color"] == pytest.approx(1.0 / 0.75) and rows[1]["ratio"][
        "base_color"
    ] == pytest.approx(0.0)
    assert rows[0]["ratio"]["roughness"] == pytest.approx(1.0) and rows[1]["ratio"]["roughness"] == pytest.approx(1.0)
    assert pooled(rows, True)["base_color"] == pytest.approx(1.0 / 0.75) and pooled(rows, False)[
        "metallic"
    ] == pytest.approx(0.0)


def test_a_batch_no_gaussian_saw_has_no_ratio():
    seen = torch.tensor([[True, False]])
    weights = {g: torch.tensor([[1.0, 0.0]]) for g in ("base_color", "roughness", "metallic")}
    rows = batch_shares(weights, seen, ["a", "b"], [batch(["a"], 0.0), batch(["b"], 0.2)])
    assert rows[1]["ratio"]["base_color"] is None and pooled(rows, True)["base_color"] is None


def test_a_run_without_a_merger_or_batches_is_refused_with_the_file(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "merger.pt: is missing" in capsys.readouterr().err
