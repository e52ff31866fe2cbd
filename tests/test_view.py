"""`matspray view` without a browser: camera conversion, light turning, bad inputs, snapshots, progressive sizes and
that every picture comes from MatSpray's renderer (tests/test_view_browser.py opens the page itself)."""

from __future__ import annotations

import json
import math
import socket
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from matspray.cli import main
from matspray.data import Camera
from matspray.data.images import read_raw, write_image
from matspray.errors import ConfigError, DataError
from matspray.export.frames import dataset_from_glb
from matspray.gaussians import quaternion_to_matrix
from matspray.render.backend import rendering_with
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.latlong import pixel_directions
from matspray.rundir import write_json
from matspray.view.camera import camera_from_viser, frame_size, matrix_to_quaternion, viser_pose
from matspray.view.frames import MODES, Progressive, progressive_size
from matspray.view.glb import glb_pose
from matspray.view.launch import light_files
from matspray.view.lights import ESTIMATED, LightChoice, LightLoader, RotatedLight, rotate_about_up
from matspray.view.photos import nearest_view
from matspray.view.snapshot import write_snapshot
from tests.scenes import ring_cameras, sky_map, write_disk_sphere_run
from tests.viewer_process import free_port


def make_view_run(root: Path, gaussians: int = 800) -> Path:
    """A run folder with the disk sphere's asset (true materials, the sky light as its estimated light) and a Blender
    dataset of 6 training and 2 test renders; returns the run folder."""
    return write_disk_sphere_run(root, gaussians, ring_cameras(8, 32), slice(0, 6), slice(6, None))


@pytest.fixture(scope="module")
def view_run(tmp_path_factory):
    return make_view_run(tmp_path_factory.mktemp("view"))


# ------------------------------------------------------------------------------------------ cameras
def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def rotation(wxyz) -> np.ndarray:  # [4] (w, x, y, z), any length > 0 -> [3, 3], by the package's one conversion
    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64))
    return quaternion_to_matrix(q / q.norm()).numpy()


def test_quaternions_round_trip_and_agree_with_viser():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = random_rotation(rng)
        q = matrix_to_quaternion(R)
        assert np.allclose(rotation(q), R, atol=1e-12)
    tf = pytest.importorskip("viser.transforms")
    for _ in range(20):
        wxyz = rng.normal(size=4)
        assert np.allclose(rotation(wxyz), tf.SO3(wxyz / np.linalg.norm(wxyz)).as_matrix(), atol=1e-12)


def test_viser_camera_projects_points_as_a_brute_force_pinhole_does():
    """viser: P_world = R p_camera + t, camera looks along +Z with -Y up, `fov` vertical. A point is projected by hand
    from that definition and must land on the pixel `Camera.project` gives."""
    rng = np.random.default_rng(1)
    for _ in range(10):
        R, t = random_rotation(rng), rng.normal(size=3) * 3
        wxyz, fov, width, height = (
            matrix_to_quaternion(R),
            rng.uniform(0.3, 1.5),
            int(rng.integers(40, 400)),
            int(rng.integers(40, 400)),
        )
        camera = camera_from_viser(wxyz, t, fov, width, height)
        p_camera = np.stack([rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20), rng.uniform(1, 5, 20)], axis=-1)
        points = p_camera @ R.T + t
        focal = (height / 2) / math.tan(fov / 2)  # vertical field of view over the image height
        expected = np.stack(
            [width / 2 + focal * p_camera[:, 0] / p_camera[:, 2], height / 2 + focal * p_camera[:, 1] / p_camera[:, 2]],
            -1,
        )
        pixels, depth = camera.project(torch.tensor(points, dtype=torch.float32))
        assert np.allclose(pixels.numpy(), expected, atol=2e-3 * width)
        assert np.allclose(depth.numpy(), p_camera[:, 2], atol=1e-4)


def test_a_look_at_camera_survives_the_trip_through_viser():
    camera = Camera.look_at([3.0, -2.0, 1.5], [0.1, 0.2, 0.3], [0.0, 0.0, 1.0], 0.8, 160, 120)
    wxyz, position, fov = viser_pose(camera)
    back = camera_from_viser(wxyz, position, fov, 160, 120)
    assert torch.allclose(back.viewmat, camera.viewmat, atol=1e-5) and torch.allclose(back.K, camera.K, atol=1e-3)
    # what viser calls "up" (-Y of the camera) is the world's +z as seen: a point above the target is above the centre
    pixels, _ = back.project(torch.tensor([[0.1, 0.2, 0.3], [0.1, 0.2, 0.8]]))
    assert abs(pixels[0, 0] - 80) < 1e-3 and abs(pixels[0, 1] - 60) < 1e-3 and pixels[1, 1] < 60


def test_frame_sizes_keep_the_aspect_and_shrink_only_while_moving():
    assert frame_size(2.0, 256) == (256, 128) and frame_size(0.5, 256) == (128, 256)
    assert progressive_size(16 / 9, 256, moving=False) == (256, 144)
    assert progressive_size(16 / 9, 256, moving=True) == (128, 72)
    assert progressive_size(1.0, 40, moving=True) == (32, 32)  # never below the minimum


def test_progressive_renders_low_while_moving_then_one_full_frame_when_still():
    p = Progressive(settle=0.25)
    p.moved(0.0)
    assert p.next(0.01) == "low"
    p.rendered("low")
    assert p.next(0.05) is None  # nothing new while the shown low frame is current
    p.moved(0.1)
    assert p.next(0.12) == "low"
    p.rendered("low")
    assert p.next(0.2) is None and 0.1 < p.wait(0.2) < 0.2  # wakes when the camera has been still long enough
    assert p.next(0.36) == "full"
    p.rendered("full")
    assert p.next(5.0) is None and p.wait(5.0) == float("inf")
    p.changed()  # a new light while still: straight to full size
    assert p.next(5.1) == "full"


# ------------------------------------------------------------------------------------------ lights
def test_rotate_about_up_turns_counter_clockwise_and_keeps_height():
    d = torch.tensor([[1.0, 0.0, 0.3], [0.0, 1.0, -0.5]])
    out = rotate_about_up(d, math.pi / 2)
    assert torch.allclose(out, torch.tensor([[0.0, 1.0, 0.3], [-1.0, 0.0, -0.5]]), atol=1e-6)


def test_a_turned_light_is_the_map_shifted_by_whole_columns_and_zero_is_exact():
    env = EnvironmentMap.from_tensor(sky_map(16), learnable=False)
    light = RotatedLight(env, env.prefilter())
    width = env.map.shape[1]
    for k in (1, 5, 11):
        turned = light.turned(2 * math.pi * k / width)
        # L'(d) = L(R(-angle) d); azimuth grows towards smaller columns, so the map moves k columns left
        assert torch.allclose(turned.source, env.map.roll(-k, dims=1), atol=1e-4, rtol=1e-4)
        d = pixel_directions(16, 32).reshape(-1, 3)
        assert torch.allclose(turned.radiance(d), env.map.roll(-k, dims=1).reshape(-1, 3), atol=1e-4, rtol=1e-4)
    # the sun moves with the turn: the turned light's brightest direction is the original's, turned
    sun = torch.nn.functional.normalize(torch.tensor([0.5, 0.3, 0.8]), dim=0)
    angle = 1.0
    turned = light.turned(angle)
    assert torch.allclose(
        turned.lookup_diffuse(rotate_about_up(sun, angle)[None]), light.lookup_diffuse(sun[None]), atol=1e-5
    )
    r = torch.tensor([0.3])
    assert torch.allclose(
        turned.lookup_specular(rotate_about_up(sun, angle)[None], r), light.lookup_specular(sun[None], r), atol=1e-5
    )
    # unturned: the very lookups of the prefiltered light
    n = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    assert torch.equal(light.turned(0.0).lookup_diffuse(n), light.prefiltered.lookup_diffuse(n))


def test_light_files_expand_folders_and_refuse_missing_paths(tmp_path):
    write_image(tmp_path / "a.exr", torch.ones(8, 16, 3))
    write_image(tmp_path / "b.hdr", torch.ones(8, 16, 3))
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in light_files([tmp_path])] == ["a.exr", "b.hdr"]
    with pytest.raises(ConfigError, match="no such file"):
        light_files([tmp_path / "missing.exr"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="no .exr or .hdr"):
        light_files([tmp_path / "empty"])


@pytest.mark.parametrize(
    "name, content, problem",
    [
        ("photo.png", None, "is not an HDR light"),
        ("broken.exr", b"this is not an OpenEXR file at all", "broken.exr"),
        ("square.exr", "square", "twice as wide as tall"),
    ],
)
def test_bad_light_files_are_one_line_naming_the_file(tmp_path, name, content, problem):
    path = tmp_path / name
    if content is None:
        write_image(path, torch.full((8, 16, 3), 0.5))
    elif content == "square":
        write_image(path, torch.ones(16, 16, 3))
    else:
        path.write_bytes(content)
    with pytest.raises(DataError) as error:
        LightLoader().load(path)
    message = str(error.value)
    assert problem in message and str(path) in message and "\n" not in message


# ------------------------------------------------------------------------------------------ the viewer, no browser
@pytest.fixture(scope="module")
def viewer(view_run):
    from matspray.view.server import Viewer, ViewerConfig

    told = []
    v = Viewer(view_run, ViewerConfig(resolution=64), device="cpu", backend="torch", notify=told.append)
    v.told = told
    yield v
    v.stop()


def test_the_viewer_starts_with_the_runs_estimated_light_and_keeps_it_after_a_bad_file(viewer, tmp_path):
    assert viewer.state.light == ESTIMATED and viewer.state.variant == "full"
    bad = tmp_path / "broken.hdr"
    bad.write_bytes(b"#?RADIANCE\nnonsense")
    label = viewer.add_light_file(bad)
    assert label is None and all(c.spec != str(bad) for c in viewer.choices)  # not offered
    assert len(viewer.told) == 1 and str(bad) in viewer.told[0] and "\n" not in viewer.told[0]
    good = viewer.light
    assert viewer.set_light("sunset") and viewer.state.light == "sunset"
    assert viewer.set_light(ESTIMATED) and viewer.light.prefiltered is good.prefiltered  # cached, not reloaded
    assert viewer.set_light("sunset")
    # an --env file that cannot be read when chosen: one line, and the last good light stays
    listed = tmp_path / "gone.exr"
    listed.write_bytes(b"garbage")
    viewer.choices.append(LightChoice("gone.exr", str(listed)))
    shown = viewer.light
    assert not viewer.set_light("gone.exr")
    assert (
        viewer.state.light == "sunset"
        and viewer.light is shown
        and len(viewer.told) == 2
        and "gone.exr" in viewer.told[1]
    )


def test_every_display_mode_draws_the_object_with_matsprays_renderer(viewer, monkeypatch):
    import matspray.view.frames as frames

    camera = ring_cameras(1, 48)[0]
    calls = []
    original = frames.render_relit
    monkeypatch.setattr(frames, "render_relit", lambda *a, **k: calls.append(1) or original(*a, **k))
    for mode in MODES:
        viewer.update(mode=mode)
        with rendering_with("torch") as use:
            frame = viewer.render(camera)
        assert use.calls["torch"] == 1, mode  # one rasterization, counted by the renderer's own record
        assert frame.image.shape == (48, 48, 3) and frame.image.dtype == np.uint8
        covered = frame.alpha > 0.9
        assert covered.float().mean() > 0.2 and (~covered).float().mean() > 0.2  # a sphere in the middle
        assert (
            np.abs(
                frame.image[covered.numpy()].astype(float).mean(0) - frame.image[~covered.numpy()].astype(float).mean(0)
            ).max()
            > 10
        ), mode
    assert len(calls) == 2  # relit and relit over light shade through relight's render_relit
    viewer.update(mode="relit")


def test_exposure_and_turn_change_the_relit_picture(viewer):
    camera = ring_cameras(1, 48)[0]
    viewer.set_light(ESTIMATED)
    base = viewer.render(camera).display
    viewer.update(exposure=1.0)
    brighter = viewer.render(camera).display
    viewer.update(exposure=0.0, turn=120.0)
    turned = viewer.render(camera).display
    viewer.update(turn=0.0)
    assert brighter.mean() > base.mean() + 0.02
    assert (turned - base).abs().mean() > 0.01
    assert torch.equal(viewer.render(camera).display, base)  # back to the start: the same picture


def test_the_viewers_picture_is_relights_picture(viewer, view_run, tmp_path):
    """Same camera, light and size: `matspray relight --background env` writes what the viewer shows in `relit over
    light`."""
    from matspray.data import load_scene

    out = tmp_path / "relit"
    assert (
        main(
            [
                "relight",
                "--run",
                str(view_run),
                "--env",
                "studio",
                "--out",
                str(out),
                "--background",
                "env",
                "--device",
                "cpu",
                "--backend",
                "torch",
            ]
        )
        == 0
    )
    scene = load_scene(json.loads((view_run / "dataset.json").read_text())["source"])
    viewer.set_light("studio")
    viewer.update(mode="relit over light", exposure=0.0, turn=0.0)
    for view in scene.test:
        frame = viewer.render(view.camera)
        written = read_raw(out / f"{view.name}_studio.png")[..., :3]  # sRGB in [0, 1], 8 bits
        difference = (frame.display - written).abs()
        assert float(difference.mean()) < 1e-3 and float(difference.max()) <= 0.5 / 255 + 1e-3
        assert np.abs(frame.image.astype(int) - np.round(written.numpy() * 255).astype(int)).max() <= 1
    viewer.update(mode="relit")


def test_a_variant_without_its_own_light_is_refused_in_one_line(viewer, view_run):
    import shutil

    shutil.copytree(view_run / "asset", view_run / "asset-no-prior")
    (view_run / "asset-no-prior" / "envmap.exr").unlink()
    try:
        viewer.set_light(ESTIMATED)
        assert not viewer.set_light(ESTIMATED, variant="no-prior")
        assert viewer.state.variant == "full" and "learned no light" in viewer.told[-1]
        assert viewer.set_light("studio", variant="no-prior") and viewer.state.variant == "no-prior"
        viewer.set_light(ESTIMATED, variant="full")
    finally:
        shutil.rmtree(view_run / "asset-no-prior")


# ------------------------------------------------------------------------------------------ snapshots, photos, glb
def test_snapshots_are_written_whole_with_unique_names(tmp_path, monkeypatch):
    image = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    first = write_snapshot(tmp_path, image, "full", "estimated (run)", "relit", stamp=0.0)
    second = write_snapshot(tmp_path, image, "full", "estimated (run)", "relit", stamp=0.0)
    assert (
        first.parent == tmp_path / "view"
        and first.name.startswith("full_estimated-run_relit_")
        and second.name.endswith("-2.png")
    )
    assert np.array_equal(np.round(read_raw(first).numpy() * 255).astype(np.uint8), image)
    import matspray.data.images as images

    def fail_halfway(path, array, bits, level):
        Path(path).write_bytes(b"\x89PNG half")
        raise OSError("No space left on device")

    monkeypatch.setattr(images, "_write_png", fail_halfway)
    with pytest.raises(OSError):
        write_snapshot(tmp_path, image, "full", "sky", "relit", stamp=0.0)
    assert sorted(p.name for p in (tmp_path / "view").iterdir()) == sorted([first.name, second.name])  # nothing partial


def test_nearest_view_is_the_one_seen_from_the_closest_direction():
    centers = np.array([[4.0, 0, 0], [0, 4.0, 0], [-4.0, 0, 0], [0, 0, 4.0]])
    assert nearest_view(centers, np.zeros(3), [10.0, 1.0, 0.5]) == 0  # far away, same direction: still the first
    assert nearest_view(centers, np.zeros(3), [0.1, 0.2, 1.0]) == 3
    assert nearest_view(centers + 1.0, np.ones(3), [0.0, 2.0, 1.0]) == 1


def glb_bytes(document: dict) -> bytes:
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    return struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text)) + struct.pack("<II", len(text), 0x4E4F534A) + text


def test_a_glb_is_placed_in_the_datasets_world_by_its_frame(tmp_path):
    path = tmp_path / "a.glb"
    plain = dataset_from_glb(path, glb_bytes({"asset": {"version": "2.0"}}))
    assert np.allclose(plain[:3, :3] @ [0, 1, 0], [0, 0, 1])  # glTF's +Y up becomes the dataset's +Z up
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 2.0, 3.0)
    marked = dataset_from_glb(
        path, glb_bytes({"asset": {"version": "2.0", "extras": {"matspray": {"dataset_from_file": moved.tolist()}}}})
    )
    assert np.allclose(marked, moved)
    wxyz, position = glb_pose(plain, (0.5, 0.0, 0.0))
    assert np.allclose(rotation(wxyz), plain[:3, :3]) and np.allclose(position, (0.5, 0.0, 0.0))
    with pytest.raises(DataError, match="a.glb"):
        dataset_from_glb(path, b"not a glb file at all, certainly")


# ------------------------------------------------------------------------------------------ the command's bad input
def test_view_of_a_folder_that_is_no_run_names_the_command_to_run_first(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nowhere"), "--device", "cpu", "--backend", "torch"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "matspray run" in err and "Traceback" not in err
    assert main(["view", str(tmp_path), "--device", "cpu", "--backend", "torch"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a MatSpray run folder" in err and "matspray run" in err


def test_view_of_a_run_without_an_asset_names_the_command_to_run_first(tmp_path, capsys):
    write_json(tmp_path / "dataset.json", {"source": str(tmp_path), "format": "blender"})
    assert main(["view", str(tmp_path), "--device", "cpu", "--backend", "torch"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no asset" in err and f"matspray run --data DATA --out {tmp_path}" in err


def test_a_port_in_use_is_one_line_with_the_port_and_what_to_pass_instead(view_run, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        assert main(["view", str(view_run), "--port", str(port), "--device", "cpu", "--backend", "torch"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        len(err.splitlines()) == 1 and f"port {port}" in err and "in use" in err and "--port" in err.split("in use")[1]
    )


def test_a_missing_env_file_is_refused_before_anything_starts(view_run, tmp_path, capsys):
    assert (
        main(
            [
                "view",
                str(view_run),
                "--env",
                str(tmp_path / "nope.exr"),
                "--port",
                str(free_port()),
                "--device",
                "cpu",
                "--backend",
                "torch",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope.exr" in err and "no such file" in err


@pytest.mark.slow
def test_the_command_prints_its_url_and_serves_the_page(view_run):
    import subprocess
    import sys
    import urllib.request

    pytest.importorskip("viser")
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "matspray",
            "view",
            str(view_run),
            "--port",
            str(port),
            "--device",
            "cpu",
            "--backend",
            "torch",
        ],
        cwd=Path(__file__).resolve().parents[1],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = process.stdout.readline().strip()
        assert first.startswith(f"matspray view: http://localhost:{port}"), (
            first,
            process.stderr.read() if process.poll() is not None else "",
        )
        assert f"ssh -L {port}:localhost:{port}" in process.stdout.readline()
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
    finally:
        process.terminate()
        process.wait(timeout=20)


def test_an_unreadable_estimated_light_starts_the_viewer_under_a_built_in(tmp_path):
    from matspray.view.server import Viewer, ViewerConfig

    run = make_view_run(tmp_path, gaussians=200)
    (run / "asset" / "envmap.exr").write_bytes(b"not an exr")
    told = []
    viewer = Viewer(run, ViewerConfig(), device="cpu", backend="torch", notify=told.append)
    assert viewer.state.light == "studio" and len(told) == 1 and "envmap.exr" in told[0] and "studio" in told[0]


def test_stop_waits_for_the_viewers_workers_and_not_for_another_viewers_tabs(view_run):
    """stop() waits for the viewer's threads that end on their own (here a warm-up render still running), so that
    none is left inside torch at exit, but not for another viewer's per-tab loop in the same process, which runs
    until that viewer stops (it used to wait 60 s for one)."""
    import threading
    import time

    from matspray.view.server import Viewer, ViewerConfig

    viewer = Viewer(view_run, ViewerConfig(), device="cpu", backend="torch", notify=lambda _: None)
    other_viewer_stopped, warm_up_done = threading.Event(), threading.Event()
    other_tab = threading.Thread(target=other_viewer_stopped.wait, name="matspray-view-99", daemon=True)
    other_tab.start()
    viewer.start_worker(lambda: (time.sleep(0.5), warm_up_done.set()), "matspray-warmup")
    try:
        start = time.monotonic()
        viewer.stop()
        assert warm_up_done.is_set() and time.monotonic() - start < 10.0
        assert other_tab.is_alive()
    finally:
        other_viewer_stopped.set()


def test_the_page_opens_before_torch_is_imported(view_run):
    """`matspray view` serves its page while torch, the asset and the light load:
    the checks and the page need no torch."""
    import subprocess
    import sys

    code = (
        "import sys; from matspray.view.launch import light_files, open_page, run_variants; "
        f"variants = run_variants({str(view_run)!r}); page = open_page('127.0.0.1', {free_port()}); "
        "print(variants, 'torch' in sys.modules, page.url.startswith('http://localhost:')); page.stop()"
    )
    printed = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert printed.returncode == 0, printed.stderr
    assert printed.stdout.split()[-2:] == ["False", "True"], printed.stdout


@pytest.mark.on_device
def test_the_viewer_renders_on_the_device_it_is_given(view_run, device):
    """`matspray view --device cuda` renders there (asset and light on the device), and the picture is that of an
    independent reference: the asset and the light read from the run folder by the readers, not the viewer, and
    rendered in float64 on the CPU. On the GPU machine `pytest --device cuda` runs this on CUDA
    (benchmarks/gpu_check.sh lists tests/test_view.py)."""
    from matspray.data.camera import Camera
    from matspray.method.asset import Asset, read_asset
    from matspray.render.shade.envmap import EnvironmentMap
    from matspray.render.shade.lights import load_envmap
    from matspray.rundir import RunDir
    from matspray.view.frames import render_frame
    from matspray.view.lights import ENV_HEIGHT, RotatedLight, estimated_light_path
    from matspray.view.server import Viewer, ViewerConfig

    on_device = Viewer(
        view_run, ViewerConfig(resolution=48), device=str(device), backend="torch", notify=lambda _: None
    )
    try:
        state, asset, light = on_device.frame_inputs()
        assert asset.gaussians.means.device.type == device.type and asset.materials.device.type == device.type
        assert light.map.device.type == device.type and state.light.startswith("estimated")
        camera = on_device.start_camera.scaled(0.25)
        there = on_device.render(camera)
    finally:
        on_device.stop()
    folder = RunDir(view_run).asset_path(state.variant)
    read = read_asset(folder)
    exact = Asset(
        read.gaussians.to(dtype=torch.float64),
        read.materials.double(),
        read.normals.double(),
        None if read.visibility is None else read.visibility.double(),
    )
    _, radiance = load_envmap(str(estimated_light_path(folder)))
    env = EnvironmentMap.from_tensor(radiance.double(), height=ENV_HEIGHT, learnable=False)
    with torch.no_grad():
        reference_light = RotatedLight(env, env.prefilter())
    on_cpu = camera.to("cpu")
    here = render_frame(
        exact, Camera(on_cpu.K.double(), on_cpu.viewmat.double(), on_cpu.width, on_cpu.height), reference_light
    )
    assert there.image.shape == here.image.shape == (camera.height, camera.width, 3)
    assert here.alpha.sum() > 0.2 * camera.width * camera.height  # the object is in the picture
    assert np.abs(there.image.astype(int) - here.image.astype(int)).max() <= 2  # 8-bit pictures, float rounding apart
    assert (there.display.double() - here.display.double()).abs().mean() < 1e-3
