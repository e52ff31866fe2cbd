"""MatSpray: relightable 3D assets from multi-view photos, by lifting 2D diffusion material
predictions onto 3D Gaussians and fusing them with a Neural Merger."""

import os

__version__ = "0.1.0"

# torch's OpenMP threads (GNU libgomp) spin for 300 000 rounds after each parallel operation before they sleep: on a
# few cores that takes the cores from the numba kernels that follow torch's operations in every training step. A
# short spin keeps torch's back-to-back small operations fast. libgomp reads it once, when torch is first imported,
# so it is set before any module imports torch; a value already set stays (docs/dev/rasterizer.md, "OpenMP's spin").
os.environ.setdefault("GOMP_SPINCOUNT", "10000")

from matspray.errors import ConfigError, DataError, MatsprayError, NumericalError, RunError

__all__ = ["ConfigError", "DataError", "MatsprayError", "NumericalError", "RunError", "__version__"]
