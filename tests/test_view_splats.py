"""`matspray view --run FILE.glb`: the viewer opens a splats glb of `matspray export --splats` as the asset it holds,
with its estimated light, and shows what it shows for the run folder the file came from (the materials are 16-bit
in the file); a file that is missing or holds no materials is refused in one line."""

from __future__ import annotations

import math

import pytest
import torch

from matspray.cli import main
from matspray.errors import MatsprayError
from matspray.view.lights import ESTIMATED
from matspray.view.server import Viewer, ViewerConfig
from tests.scenes import ring_cameras, write_disk_sphere_run


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("view-splats")
    run = write_disk_sphere_run(root, 600, ring_cameras(3, 48), slice(None), slice(0, 1))
    assert main(["export", "--run", str(run), "--splats", str(root / "disks.glb")]) == 0
    return run, root / "disks.glb"


def viewer_of(source) -> Viewer:
    return Viewer(source, ViewerConfig(resolution=64), device="cpu", backend="torch", notify=lambda _: None)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return -10 * math.log10(max(float(((a - b) ** 2).mean()), 1e-12))


@pytest.mark.slow
def test_the_viewer_shows_a_splats_glb_as_the_run_it_came_from(exported):
    run, glb = exported
    from_run, from_file = viewer_of(run), viewer_of(glb)
    try:
        assert from_file.run.variants == ["disks"] and from_file.run.glbs == [] and from_file.run.photos() == []
        assert from_file.state.light == ESTIMATED  # the file's own light, as a run's envmap.exr
        camera = from_run.run.start_camera("full", 64, 64)
        assert torch.allclose(camera.viewmat, from_file.run.start_camera("disks", 64, 64).viewmat, atol=1e-4)
        run_frame, file_frame = from_run.render(camera).display, from_file.render(camera).display
        drawn = (run_frame - run_frame[0, 0]).abs().sum(-1) > 0.05
        assert drawn.float().mean() > 0.2
        value = psnr(run_frame, file_frame)
        print(f"\nthe viewer's frame of the splats glb against its run's: {value:.1f} dB")
        assert value > 40  # the figure for relight; 16-bit materials give far more
    finally:
        from_run.stop()
        from_file.stop()


def test_a_missing_file_or_one_without_materials_is_refused_in_one_line(exported, tmp_path, capsys):
    from matspray.gltf.splats import read_splats_glb, write_splats_glb

    missing = tmp_path / "none.glb"
    assert main(["view", "--run", str(missing)]) != 0
    err = capsys.readouterr().err
    assert f"{missing}: no such file" in err and "--splats" in err and err.strip().count("\n") == 0
    splats, _ = read_splats_glb(exported[1])
    splats.base_color = None
    bare = tmp_path / "bare.glb"
    write_splats_glb(bare, splats)
    with pytest.raises(MatsprayError) as raised:
        viewer_of(bare)
    message = str(raised.value)
    assert str(bare) in message and "no MatSpray materials" in message and "\n" not in message
