"""One picture of the asset per display mode, and which size to render it at.

Every mode goes through `matspray.method.relight` (`render_relit`, `render_gbuffer`, `background_radiance`): the relit
modes are `relight`'s own computation, so with exposure 0 and the light unturned the viewer shows what `relight` writes
(`relit over light` is `relight --background env`). The display is sRGB like the PNGs MatSpray writes: base colour
sRGB-encoded, roughness, metallic and alpha as their linear values in grey, normals as 0.5 + 0.5 n (world space).

Progressive rendering: while the camera moves, frames are rendered at a fraction of the size; once it has been still
for `settle` seconds, one frame at full size follows (`Progressive`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.images import linear_to_srgb
from matspray.method.asset import Asset
from matspray.method.relight import background_radiance, render_gbuffer, render_relit

MODES = ("relit", "relit over light", "base colour", "roughness", "metallic", "normals", "alpha")
BACKDROP = 0.05  # linear grey behind the object where the light is not drawn (sRGB ~0.25: dark, not black)


@dataclass(frozen=True)
class FrameSettings:
    mode: str = "relit"
    exposure: float = 0.0  # stops: the relit picture is scaled by 2^exposure before display

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"display mode '{self.mode}': choose one of {', '.join(MODES)}")


@dataclass
class Frame:
    image: np.ndarray  # [H, W, 3] uint8, sRGB: what the page shows
    display: Tensor  # [H, W, 3] float in [0, 1] before quantisation (what `image` rounds)
    alpha: Tensor  # [H, W] coverage
    seconds: float  # rendering and encoding, without sending

    @property
    def size(self) -> tuple[int, int]:  # (width, height)
        return self.image.shape[1], self.image.shape[0]


def render_frame(asset: Asset, camera: Camera, light, settings: FrameSettings = FrameSettings()) -> Frame:
    """The picture of `asset` seen by `camera` under `light` (a `lights.RotatedLight`, or anything `render_relit`
    takes) in the display mode of `settings`. Call inside `rendering_with(backend)` to choose the rasterizer."""
    start = time.perf_counter()
    with torch.no_grad():
        if settings.mode in ("relit", "relit over light"):
            rgb, alpha = render_relit(asset, camera, light)  # premultiplied: over black
            if settings.mode == "relit over light":  # as `relight --background env` composites
                rgb = rgb + background_radiance(light, camera) * (1 - alpha[..., None])
                linear = rgb * 2.0**settings.exposure
            else:
                linear = rgb * 2.0**settings.exposure + BACKDROP * (1 - alpha[..., None])
            display = linear_to_srgb(linear)
        else:
            gbuffer = render_gbuffer(asset, camera)
            alpha = gbuffer.alpha
            values = {
                "base colour": lambda: linear_to_srgb(gbuffer.base_color.clamp(0, 1)),
                "roughness": lambda: gbuffer.roughness[..., None].expand(-1, -1, 3),
                "metallic": lambda: gbuffer.metallic[..., None].expand(-1, -1, 3),
                "normals": lambda: 0.5 + 0.5 * torch.nn.functional.normalize(gbuffer.normals, dim=-1, eps=1e-12),
                "alpha": lambda: torch.ones_like(gbuffer.normals),
            }[settings.mode]().clamp(0, 1)
            backdrop = float(linear_to_srgb(torch.tensor(BACKDROP)))
            if settings.mode == "alpha":  # coverage itself: white where covered, black where not
                display = alpha[..., None].expand(-1, -1, 3)
            else:
                display = values * alpha[..., None] + backdrop * (1 - alpha[..., None])
        display = display.float().cpu()
        image = (display.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
    return Frame(image, display, alpha.cpu(), time.perf_counter() - start)


def progressive_size(
    aspect: float, long_side: int, moving: bool, moving_scale: float = 0.5, minimum: int = 32
) -> tuple[int, int]:
    """(width, height) to render at: the full `long_side` when the camera is still, `moving_scale` of it (at least
    `minimum` pixels) while it moves."""
    from matspray.view.camera import frame_size

    side = long_side if not moving else max(minimum, min(long_side, round(long_side * moving_scale)))
    return frame_size(aspect, side)


class Progressive:
    """When to render what, for one view: `moved(now)` on every camera change, `changed()` on any other change (light,
    mode, size). `next(now)` says what to render now: 'low' while the camera moves, 'full' once it has been still
    for `settle` seconds (or for a change that is not motion), None when the picture shown is current. `rendered(kind)`
    after each frame. Times are plain seconds, so it is tested without waiting."""

    def __init__(self, settle: float = 0.25):
        self.settle = settle
        self.last_move = -float("inf")
        self.pending = True  # nothing shown yet
        self.shown: str | None = None

    def moved(self, now: float) -> None:
        self.last_move, self.pending = now, True

    def changed(self) -> None:
        self.pending = True

    def moving(self, now: float) -> bool:
        return now - self.last_move < self.settle

    def next(self, now: float) -> str | None:
        if self.moving(now):
            return "low" if self.pending else None
        if self.pending or self.shown == "low":
            return "full"
        return None

    def rendered(self, kind: str) -> None:
        self.pending, self.shown = False, kind

    def wait(self, now: float) -> float:
        """Seconds until `next` may change its answer without a new event (the camera settling)."""
        return max(0.0, self.last_move + self.settle - now) if self.shown == "low" or self.pending else float("inf")
