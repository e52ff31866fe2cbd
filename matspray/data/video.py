"""Writing frames as a video (the `video` extra: imageio-ffmpeg's own ffmpeg binary)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from matspray.data.images import atomic_target


def write_video(frames: list[Tensor], path, fps: int) -> None:
    """Frames [H, W, 3] in [0, 1] (sRGB) -> an H.264 MP4, written atomically."""
    import imageio_ffmpeg  # optional dependency (extra `video`)

    height, width = frames[0].shape[:2]
    tmp = atomic_target(Path(path))
    writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, quality=8, macro_block_size=1)
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray((frame.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()))
    writer.close()
    os.replace(tmp, path)
