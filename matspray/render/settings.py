"""The blending rules the rasterizer, the frozen-view weights and the ray tracer share (3DGS's).

The defaults are gsplat 1.5's (its `rasterization` defaults and the constants compiled into its kernels), so the
backends torch and gsplat draw the same image: near_plane 0.01 and eps2d 0.3 are passed to gsplat, and
min_alpha, max_alpha and min_transmittance are its ALPHA_THRESHOLD (1/255), min(0.999f, ...) and the 1e-4 stop.
tests/test_gsplat_parity.py checks each on scenes with opaque Gaussians (opacity up to exactly 1). gsplat
cannot be given other values for the last three: with other settings, backend gsplat still uses its own.

Differences left between the backends, each covered by a test there:
  - the transmittance stop: gsplat stops before a hit that would leave T <= 1e-4 (T a float32 product), we
    before one that would leave T < 1e-4 (T from a float64 sum of logs): they differ only for a hit that
    lands on 1e-4 to within float32 rounding;
  - the near plane: gsplat draws a centre exactly on it (z == near), we do not;
  - a footprint that is singular (possible only with eps2d = 0): gsplat culls det <= 0, we det <= 1e-12 relative;
  - the projection Jacobian is evaluated with the centre's direction clamped to the image's half-extent plus
    a margin of 30 % of the half-width (gsplat: cx / fx + 0.15 W / fx; ours 1.3 cx / fx): the same for a
    centred principal point, as Camera.from_fov_x makes; otherwise Gaussians whose centre lies beyond the
    clamp, well outside the image, get other footprints;
  - which Gaussians count as drawn (`RasterOutput.visible`), only for Gaussians that blend into no pixel: see
    matspray.render.raster.gsplat.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RasterSettings:
    near: float = 0.01  # hits closer to the camera than this (camera z) are ignored
    eps2d: float = 0.3  # rasterizer: added to the projected 2D covariance's diagonal (pixels^2), as in 3DGS
    min_alpha: float = 1.0 / 255.0  # hits with a smaller alpha are skipped
    max_alpha: float = 0.999  # alphas are clamped to this (gsplat's kernels; 3DGS's CUDA code clamps at 0.99)
    min_transmittance: float = 1e-4  # a ray stops before its transmittance would fall below this
