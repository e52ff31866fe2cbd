"""Turntable videos: any frame size, odd ones included (H.264's 4:2:0 chroma needs even sizes)."""

import pytest
import torch

from matspray.data.formats.video import write_video


@pytest.mark.parametrize("height, width", [(17, 24), (24, 17), (171, 256)])
def test_odd_sized_frames_make_a_video_of_the_frames(tmp_path, height, width):
    pytest.importorskip("imageio_ffmpeg")
    frames = [torch.full((height, width, 3), value) for value in (0.1, 0.5, 0.9)]
    path = tmp_path / "orbit.mp4"
    write_video(frames, path, fps=4)
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    assert tuple(meta["size"]) == (width + width % 2, height + height % 2)
    means = [sum(frame) / len(frame) / 255 for frame in reader]
    assert len(means) == 3
    assert [round(m, 1) for m in means] == [0.1, 0.5, 0.9]
    assert not list(tmp_path.glob("*.tmp*"))
