"""Start-up hook for the GPU scripts (benchmarks/gsplat_prebuilt/use.sh puts this folder on PYTHONPATH when
GSPLAT_PREBUILT names an earlier call's build): with GSPLAT_PREBUILT_SO set, gsplat's CUDA extension built by an
earlier call on the same machine image is imported as `gsplat.csrc`, which gsplat tries before compiling its sources
(about 80 s of a GPU lease each time). A build that does not load here (another torch or CUDA) is skipped with one
line, and gsplat compiles as usual."""

import os

if os.environ.get("GSPLAT_PREBUILT_SO"):
    import importlib.util
    import sys

    try:
        import torch  # noqa: F401 (the extension links against torch's libraries, loaded by this import)

        spec = importlib.util.spec_from_file_location("gsplat_cuda", os.environ["GSPLAT_PREBUILT_SO"])
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules["gsplat.csrc"] = module
    except Exception as exc:  # noqa: BLE001 (any failure means: compile instead)
        print(f"gsplat prebuilt extension not used ({type(exc).__name__}: {exc}); gsplat compiles it", file=sys.stderr)
        os.environ.pop("GSPLAT_PREBUILT_SO")
