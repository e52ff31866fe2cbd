"""Start-up hook for the GPU scripts (benchmarks/gpu_units.sh puts this folder on PYTHONPATH when GSPLAT_PREBUILT
names an earlier call's build): with GSPLAT_PREBUILT_SO set, gsplat's CUDA extension built by an earlier call on
the same machine image is imported as `gsplat.csrc`, which gsplat tries before compiling its sources (about 80 s of
a GPU lease each time)."""

import os

if os.environ.get("GSPLAT_PREBUILT_SO"):
    import importlib.util
    import sys

    import torch  # noqa: F401 (the extension links against torch's libraries, loaded by this import)

    spec = importlib.util.spec_from_file_location("gsplat_cuda", os.environ["GSPLAT_PREBUILT_SO"])
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["gsplat.csrc"] = module
