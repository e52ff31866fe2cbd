"""What one refinement step dispatches (`benchmarks.step_cost`): no host synchronisation between log steps, and no
more torch operations than MAX_OPERATIONS (what a step took when this test was written, and about 10 % room): each
is a kernel launch on a GPU. The CPU's step runs the merger's channel groups a product each
(`matspray.method.merger.batched_products`); the GPU path's count is tests/test_refine_terms.py's."""

import torch

from benchmarks.step_cost import measure

MAX_OPERATIONS = 1030


def test_a_refinement_step_never_waits_for_the_device_and_stays_small():
    figures = measure("refine", "cpu", torch.device("cpu"))
    assert figures["host_syncs"] == 0, figures["sync_kinds"]
    assert figures["operations"] <= MAX_OPERATIONS, figures["top_operations"]
