"""MatSpray: relightable 3D assets from multi-view photos, by lifting 2D diffusion material
predictions onto 3D Gaussians and fusing them with a Neural Merger."""

__version__ = "0.1.0"

from matspray.errors import ConfigError, DataError, MatsprayError, NumericalError, RunError

__all__ = ["ConfigError", "DataError", "MatsprayError", "NumericalError", "RunError", "__version__"]
