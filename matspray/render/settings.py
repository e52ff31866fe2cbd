"""The blending rules the rasterizer, the frozen-view weights and the ray tracer share (3DGS's)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RasterSettings:
    near: float = 0.01  # hits closer to the camera than this (camera z) are ignored
    eps2d: float = 0.3  # rasterizer: added to the projected 2D covariance's diagonal (pixels^2), as in 3DGS
    min_alpha: float = 1.0 / 255.0  # hits with a smaller alpha are skipped
    max_alpha: float = 0.99  # alphas are clamped to this
    min_transmittance: float = 1e-4  # a ray stops before its transmittance would fall below this
