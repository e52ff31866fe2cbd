"""Writing frames as a video (the `video` extra: imageio-ffmpeg's own ffmpeg binary)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from matspray.data.images import atomic_target
from matspray.errors import file_error, optional_module


def write_video(frames: list[Tensor], path, fps: int) -> None:
    """Frames [H, W, 3] in [0, 1] (sRGB) -> an H.264 MP4, written atomically."""
    imageio_ffmpeg = optional_module("imageio_ffmpeg", "video", "writing a video")

    height, width = frames[0].shape[:2]
    # H.264 in yuv420p halves the chroma resolution: odd sizes are refused, so an odd last row or column is repeated
    even_height, even_width = height + height % 2, width + width % 2
    tmp = atomic_target(Path(path))
    writer = imageio_ffmpeg.write_frames(str(tmp), (even_width, even_height), fps=fps, quality=8, macro_block_size=1)
    try:
        writer.send(None)
        for frame in frames:
            pixels = (frame.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
            pixels = np.pad(pixels, ((0, even_height - height), (0, even_width - width), (0, 0)), mode="edge")
            writer.send(np.ascontiguousarray(pixels))
        writer.close()
    except (OSError, RuntimeError) as exc:  # ffmpeg refused the stream: say so in one line, leave nothing behind
        tmp.unlink(missing_ok=True)
        raise file_error(
            Path(path),
            "the video encoder (ffmpeg) failed: "
            f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__}",
            "the PNG frames are written; try another frame rate",
        ) from None
    os.replace(tmp, path)
