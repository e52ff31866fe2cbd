"""What one refinement step dispatches (`benchmarks.step_cost`): no host synchronisation between log steps, and no
more torch operations than MAX_OPERATIONS (what a step took when this test was written, and about 10 % room): each
is a kernel launch on a GPU."""

import torch

from benchmarks.step_cost import measure

MAX_OPERATIONS = 790


def test_a_refinement_step_never_waits_for_the_device_and_stays_small():
    figures = measure("refine", "cpu", torch.device("cpu"))
    assert figures["host_syncs"] == 0, figures["sync_kinds"]
    assert figures["operations"] <= MAX_OPERATIONS, figures["top_operations"]
