"""The benchmarks: development measurements, not part of the product.

They score LPIPS with the weights of the shared test data when a developer machine has them beside the repository
(`../shared/data/lpips`) and nothing else is set: a user's `matspray eval` never looks there (it takes
torchvision's AlexNet from torch's cache, `matspray.eval.lpips`). The variable reaches the commands the benchmarks
start as well."""

import os
from pathlib import Path

SHARED_LPIPS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lpips" / "lpips_alexnet_v0.1.npz"

if "MATSPRAY_LPIPS_WEIGHTS" not in os.environ and SHARED_LPIPS.is_file():
    os.environ["MATSPRAY_LPIPS_WEIGHTS"] = str(SHARED_LPIPS.resolve())
