"""Backend `gsplat` of `rasterize`: the same blending rule, one CUDA call (`gsplat.rasterization`, gsplat 1.5).

gsplat is an optional extra (`pip install 'matspray[cuda]'`), imported here only when this backend runs.

Conventions (gsplat/rendering.py's API):
  - quats are (w, x, y, z), need not be unit length: ours are stored that way;
  - scales and opacities are activated values: we pass exp(log_scales) and sigmoid(opacity_logits);
  - viewmats are world-to-camera [C, 4, 4], Ks [C, 3, 3]: our Camera's viewmat (OpenCV axes) and K;
  - with sh_degree=None, colors [N, D] are rendered as they are (any D);
  - render_mode "RGB+D" appends the accumulated depth sum_k w_k z_k as the last channel ("ED" would
    divide it by alpha); our RasterOutput.depth is the accumulated one, and the expected depth comes from
    RasterOutput.expected_depth, as for backend torch;
  - RasterSettings equal gsplat's kernels (see matspray.render.settings for the differences left).
The background is composited here, (1 - alpha) * background, rather than through gsplat's `backgrounds`, so
that the depth channel never receives it.

What we return, so that both backends mean the same (RasterOutput):
  - screen = meta["means2d"] [1, N, 2], the tensor in the graph: d loss / d means2d and, with absgrad=True,
    gsplat's means2d.absgrad (sum over pixels of |d loss_pixel / d means2d|) are read from it;
  - means2d = its values [N, 2], zero where not drawn (gsplat leaves those entries unwritten);
  - radii = the 3-sigma radius of the major axis of the 2D covariance (from gsplat's conics), 0 where gsplat
    did not draw the Gaussian (its radii, integer per-axis opacity-aware box half-sizes, are 0), as backend torch.
    Besides the settings' differences (matspray.render.settings: a centre exactly on the near plane), "drawn"
    differs only for Gaussians that blend into no pixel on either backend: gsplat draws a
    Gaussian when its integer box ceil(extend * sigma_axis) around the centre overlaps the image (extend =
    sqrt(2 ln(255 opacity))), torch when its footprint ellipse contains a pixel centre, so a footprint just
    outside the image edge or one that falls between pixel centres is visible on gsplat only (and counted in
    densification's statistics there; its screen-space gradient is 0 on both);
  - tile_hits = the (Gaussian, 16 x 16 tile) pairs gsplat evaluated (torch counts blended (Gaussian, pixel) pairs).

tests/test_gsplat_parity.py runs this module through gsplat's own Python code on the CPU (tests/gsplat_cpu.py:
its CUDA calls replaced by its torch references and a torch copy of the blending kernel) and checks it against
backend torch: images, alpha, depths, means2d, radii, every gradient, absgrad, densification statistics.
Left to a GPU (test_gsplat_matches_torch_on_cuda, skipped without one; not run yet): gsplat's CUDA build and the
arithmetic of its kernels, compiled with -use_fast_math (__expf / __logf can move a hit that sits on the 1/255
alpha threshold or the 1e-4 transmittance stop), and its float32 sums in another order (atomicAdd in the backward).
"""

from __future__ import annotations

import importlib

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.gaussians import Gaussians
from matspray.render.output import RasterOutput
from matspray.render.projection import max_eigen_radius
from matspray.render.settings import RasterSettings

COMPILED_SETTINGS = ("min_alpha", "max_alpha", "min_transmittance")  # constants in gsplat's kernels, not arguments
GSPLAT_CHANNEL_CHUNK = 32  # gsplat.rasterization's default: more channels are rendered in chunks of this many


def rasterize_gsplat(
    gaussians: Gaussians,
    camera: Camera,
    features: Tensor,  # [N, C]
    background: Tensor | None,  # [C] or None
    settings: RasterSettings,
    absgrad: bool = False,
) -> RasterOutput:
    check_compiled_settings(settings)
    gsplat = importlib.import_module("gsplat")
    channels = features.shape[1] + 1  # + the depth channel
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
        absgrad=absgrad,
        # each chunk's backward replaces means2d.absgrad with its own: with absgrad, one chunk for all channels
        channel_chunk=max(GSPLAT_CHANNEL_CHUNK, channels) if absgrad else GSPLAT_CHANNEL_CHUNK,
    )
    image, alpha = colors[0], alphas[0, ..., 0]  # [H, W, C + 1], [H, W]
    out = image[..., :-1]
    if background is not None:
        out = out + (1.0 - alpha)[..., None] * background.to(out)
    screen = meta["means2d"]  # [1, N, 2]
    drawn = (meta["radii"][0] > 0).all(dim=-1)  # [N]
    with torch.no_grad():
        means2d = torch.where(drawn[:, None], screen[0], torch.zeros_like(screen[0]))  # [N, 2]
        major = max_eigen_radius(covariance_of_conics(meta["conics"][0]))  # [N], garbage where not drawn
        radii = torch.where(drawn, major, torch.zeros_like(major))
    return RasterOutput(
        features=out,
        alpha=alpha,
        depth=image[..., -1],
        means2d=means2d,
        radii=radii,
        backend="gsplat",
        screen=screen,
        tile_hits=int(meta["flatten_ids"].numel()),
    )


def sh_colors_gsplat(
    sh: Tensor,  # [N, K, 3] coefficients
    means: Tensor,  # [N, 3]
    center: Tensor,  # [3] camera centre
    degree: int,
) -> Tensor:  # [N, 3] colour, >= 0: `matspray.render.shade.sh.sh_to_rgb` of the directions from the camera
    """SH colour by gsplat's fused kernels (it normalises the directions itself; their gradient reaches `means`)."""
    gsplat = importlib.import_module("gsplat")
    coefficients = gsplat.spherical_harmonics(degree, means - center.to(means), sh)
    return torch.clamp_min(coefficients + 0.5, 0.0)


def check_compiled_settings(settings: RasterSettings) -> None:
    """gsplat's kernels have min_alpha, max_alpha and min_transmittance compiled in (our defaults): refuse others
    rather than draw with values the caller did not ask for."""
    default = RasterSettings()
    changed = [
        f"{name}={getattr(settings, name)}"
        for name in COMPILED_SETTINGS
        if getattr(settings, name) != getattr(default, name)
    ]
    if changed:
        raise ValueError(
            f"rasterize: backend gsplat has {', '.join(COMPILED_SETTINGS)} compiled in (the RasterSettings "
            f"defaults); got {', '.join(changed)}: use backend torch for other values"
        )


def covariance_of_conics(
    conics: Tensor,
) -> Tensor:  # [N, 3] (a, b, c) of [[a, b], [b, c]] -> [N, 3] (xx, xy, yy) of its inverse
    a, b, c = conics.unbind(-1)
    det = a * c - b * b
    return torch.stack([c / det, -b / det, a / det], dim=-1)
