"""Backend `gsplat` of `rasterize`: the same blending rule, one CUDA call (`gsplat.rasterization`).

gsplat is an optional extra (`pip install 'matspray[cuda]'`), imported here only when this backend runs.

Conventions, checked against gsplat's documented API (gsplat/rendering.py docstring):
  - quats are (w, x, y, z), need not be unit length: ours are stored that way;
  - scales and opacities are activated values: we pass exp(log_scales) and sigmoid(opacity_logits);
  - viewmats are world-to-camera [C, 4, 4], Ks [C, 3, 3]: our Camera's viewmat (OpenCV axes) and K;
  - with sh_degree=None, colors [N, D] are rendered as they are (any D; slower above 32);
  - render_mode "RGB+D" appends the accumulated depth sum_k w_k z_k as the last channel ("ED" would
    divide it by alpha); our RasterOutput.depth is the accumulated one, so we ask for "RGB+D" and the
    expected depth comes from RasterOutput.expected_depth, as for backend torch;
  - near_plane and eps2d have the same meaning and defaults (0.01, 0.3) as our RasterSettings.
To verify on a GPU (not measured yet; tests/test_gsplat_backend.py does it where CUDA is present):
  - that gsplat's pixel centres are at +0.5 like ours (its kernels sample at i + 0.5);
  - its alpha threshold (1/255), alpha clamp and early-stop transmittance against RasterSettings;
  - the layout of meta["radii"] ([C, N] or [C, N, 2] depending on the version; both are handled).
The background is composited here, (1 - alpha) * background, rather than through gsplat's
`backgrounds`, so that the depth channel never receives it.
"""

from __future__ import annotations

import importlib

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.settings import RasterSettings


def rasterize_gsplat(
    gaussians: Gaussians,
    camera: Camera,
    features: Tensor,  # [N, C]
    background: Tensor | None,  # [C] or None
    settings: RasterSettings,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, int]:
    """features [H, W, C], alpha [H, W], accumulated depth [H, W], means2d [N, 2], radii [N], hits."""
    gsplat = importlib.import_module("gsplat")
    colors, alphas, meta = gsplat.rasterization(
        gaussians.means.float().contiguous(),
        gaussians.quats.float().contiguous(),
        gaussians.scales.float().contiguous(),
        gaussians.opacities.float().contiguous(),
        features.float().contiguous(),
        camera.viewmat[None].float(),
        camera.K[None].float(),
        camera.width,
        camera.height,
        near_plane=settings.near,
        eps2d=settings.eps2d,
        sh_degree=None,
        packed=False,  # meta keeps the [C, N, ...] layout, so means2d and radii are per Gaussian
        render_mode="RGB+D",
    )
    image, alpha = colors[0], alphas[0, ..., 0]  # [H, W, C + 1], [H, W]
    out = image[..., :-1]
    if background is not None:
        out = out + (1.0 - alpha)[..., None] * background.to(out)
    radii = meta["radii"][0]
    if radii.dim() == 2:  # newer gsplat: per-axis radii [N, 2]
        radii = radii.max(dim=-1).values
    hits = int(meta["flatten_ids"].numel()) if meta.get("flatten_ids") is not None else 0  # (Gaussian, tile) pairs
    return out, alpha, image[..., -1], meta["means2d"][0], radii.to(out.dtype), hits
