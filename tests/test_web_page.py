"""`matspray export --web DIR`: the page's data (quantised within its steps) and the page itself in headless
chromium with software WebGL, opened from file://: it draws the object, relights it under another light or a
dropped .exr, matches `matspray relight`'s frame, and its frame time is measured. The browser tests skip, with the
reason, where chromium, its driver, selenium or the page's script (built by `make setup` with npm) are missing."""

from __future__ import annotations

import base64
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.web_fps import milliseconds_per_frame, open_page, write_disk_sphere_page
from benchmarks.web_match import frame, psnr_inside, show
from matspray.cli import main
from matspray.method.asset import Asset, read_asset
from matspray.web.pack import LIGHT_HEIGHT, deflated, page_light, quantise_asset, srgb_encode, unpack_asset
from matspray.web.page import BACKGROUND, BUNDLE
from tests.browser import headless_chromium, missing_browser
from tests.scenes import sky_map, sphere_cameras, sphere_of_disks, write_disk_sphere_run

BACKGROUND = np.array(BACKGROUND)  # the page's, linear
PSNR_FLOOR = 45.0  # the page drawing every Gaussian, inside the object; measured 52-58 dB (docs/dev/web.md)
ISSUE_PSNR = 30.0  # the issue's target, for the page as exported by default


def test_the_page_data_keeps_every_value_within_its_step():
    g, normals, materials = sphere_of_disks(300)
    materials[:, 3] = torch.rand(300, generator=torch.Generator().manual_seed(0))
    meta, arrays = quantise_asset(Asset(g, materials, normals))
    back = unpack_asset(meta, arrays)
    span = np.array(meta["positionMax"]) - np.array(meta["positionMin"])
    assert (np.abs(back["means"] - g.means.double().numpy()) <= span / 65535 / 2 + 1e-9).all()
    log_span = meta["logScaleMax"] - meta["logScaleMin"]
    assert np.abs(np.log(back["scales"]) - g.log_scales.double().numpy()).max() <= log_span / 65535 / 2 + 1e-9
    assert np.abs(back["opacities"] - g.opacities.double().numpy()).max() <= 0.5 / 255 + 1e-9
    assert np.abs(back["roughness"] - materials[:, 3].double().numpy()).max() <= 0.5 / 255 + 1e-9
    assert np.abs(back["normals"] - normals.double().numpy()).max() <= 0.5 / 32767 + 1e-9
    # base colour: 8 bits of its sRGB encoding, as glTF textures hold it: half a step there
    encode = lambda x: np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)  # noqa: E731
    assert np.abs(encode(back["base_color"]) - encode(materials[:, :3].double().numpy())).max() <= 0.5 / 255 + 1e-6
    rotation_error = np.minimum(
        np.abs(back["rotations"] - g.rotations.double().numpy()).max(1),
        np.abs(back["rotations"] + g.rotations.double().numpy()).max(1),
    )
    assert rotation_error.max() < 2 / 32767
    layout, data = deflated(arrays)
    assert sum(len(a.tobytes()) for a in arrays.values()) == 32 * 300  # 32 bytes a Gaussian before deflating
    assert layout["position"] == {"type": "u16", "offset": 0, "length": 900} and len(data) > 0


def test_a_light_keeps_its_rows_when_it_has_fewer_than_the_pages():
    assert page_light(sky_map(16)).shape == (16, 32, 3)
    assert page_light(torch.ones(128, 256, 3)).shape == (LIGHT_HEIGHT, 2 * LIGHT_HEIGHT, 3)


def test_without_its_script_the_page_is_refused_in_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    import matspray.web.page as page_module

    monkeypatch.setattr(page_module, "BUNDLE", tmp_path / "missing.js")
    assert main(["export", "--run", str(tmp_path / "no-run"), "--web", str(tmp_path / "web")]) == 2
    err = capsys.readouterr().err
    assert "missing.js is not built" in err and "make setup" in err and err.count("\n") == 1
    assert not (tmp_path / "web").exists()


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The disk sphere's run (64 px cameras), its page drawing every Gaussian and `matspray relight`'s orbit frames
    under the sunset and under the run's own light file, at the page's light resolution: (run, page folder, relight
    folder). The page as export makes it by default (fewer Gaussians: web.detail) is beside them, in "default"."""
    reason = missing_browser({BUNDLE: f"the page's script {BUNDLE} is not built (`make setup` builds it with npm)"})
    if reason is not None:
        pytest.skip(reason)
    root = tmp_path_factory.mktemp("web")
    run = write_disk_sphere_run(root, 1500, sphere_cameras(6, 64), slice(None), slice(0, 1))
    assert main(["export", "--run", str(run), "--web", str(root / "page"), "inf"]) == 0
    assert main(["export", "--run", str(run), "--web", str(root / "default")]) == 0
    estimated = str(run / "asset" / "envmap.exr")
    relight = ["relight", "--run", str(run), "--env", "sunset", estimated, "--views", "orbit", "--frames", "2"]
    assert main([*relight, "--env-height", str(LIGHT_HEIGHT), "--out", str(root / "relit"), "--backend", "torch"]) == 0
    return run, root / "page", root / "relit"


@pytest.fixture(scope="module")
def page(site):
    driver = headless_chromium(1000, 800)
    driver.set_script_timeout(300)
    try:
        open_page(driver, site[1])  # file://: no server
        yield driver
    finally:
        driver.quit()


def orbit(run, frames=2):
    from matspray.cli.relight import relight_source

    return [c for _, c in relight_source(run, "orbit", None, frames, "cpu")[1]]


@pytest.mark.slow
def test_the_page_opens_from_file_and_draws_the_object(site, page):
    from matspray.render.raster.rasterize import rasterize

    run, _, _ = site
    camera = orbit(run)[1]
    shown = show(page, camera, "estimated")
    drawn = np.abs(shown - srgb_encode(BACKGROUND)).sum(-1) > 0.02
    asset = read_asset(run / "asset")
    with torch.no_grad():
        alpha = rasterize(asset.gaussians, camera, torch.ones(len(asset.gaussians), 1)).alpha.numpy()
    expected = alpha > 0.05
    iou = (drawn & expected).sum() / (drawn | expected).sum()
    assert expected.mean() > 0.2 and iou > 0.9, (drawn.mean(), expected.mean(), iou)
    assert page.execute_script("return window.matspray.lights()")[:2] == ["estimated", "sky"]


SCRIPT_INTERFACE = {"ready", "error", "lights", "setLight", "setTurn", "setExposure", "setCamera"}
TEST_HOOKS = {"viewer", "timeFrames", "moving", "blends", "drawnAs", "forceShape", "timePrefilter"}


@pytest.mark.slow
def test_the_page_offers_its_test_hooks_only_when_its_address_asks(site, page):
    # the same shipped script either way: the tests exercise the page as it ships (src/hooks.js says why)
    try:
        open_page(page, site[1], hooks=False)
        assert set(page.execute_script("return Object.keys(window.matspray)")) == SCRIPT_INTERFACE
        assert "Gaussians" in page.execute_script("return document.getElementById('status').textContent")
    finally:
        open_page(page, site[1])
    assert set(page.execute_script("return Object.keys(window.matspray)")) == SCRIPT_INTERFACE | TEST_HOOKS


@pytest.mark.slow
def test_the_page_matches_matspray_relight_inside_the_object(site, page):
    from matspray.data.images import read_image

    run, _, relit = site
    for i, camera in enumerate(orbit(run)):
        for light, file_light in (("sunset", "sunset"), ("estimated", "envmap")):
            rgb, alpha = read_image(relit / f"orbit_{i:03d}_{file_light}.png")
            inside = alpha.numpy() > 0.99
            reference = srgb_encode(rgb.numpy())
            value = psnr_inside(show(page, camera, light), reference, inside)
            shape = page.execute_script("return window.matspray.drawnAs()")
            print(
                f"\npage against matspray relight, orbit frame {i}, {light}: {value:.1f} dB inside the object {shape}"
            )
            assert inside.mean() > 0.2 and value > PSNR_FLOOR, (i, light, value)
    try:  # the page as exported by default draws fewer Gaussians, within web.detail's PSNR of them all
        open_page(page, site[1].parent / "default")
        status = page.execute_script("return document.getElementById('status').textContent")
        for i, camera in enumerate(orbit(run)):
            rgb, alpha = read_image(relit / f"orbit_{i:03d}_sunset.png")
            value = psnr_inside(show(page, camera, "sunset"), srgb_encode(rgb.numpy()), alpha.numpy() > 0.99)
            print(f"\nthe default page ({status}) against matspray relight, orbit frame {i}: {value:.1f} dB")
            assert value > ISSUE_PSNR and "of the asset's 1500 Gaussians" in status, (value, status)
    finally:
        open_page(page, site[1])


@pytest.mark.slow
def test_a_gaussian_in_one_triangle_draws_what_its_rectangle_draws(site, page):
    # both enclose the footprint's 1/255 alpha contour, outside which a fragment blends nothing
    camera = orbit(site[0])[1]
    show(page, camera, "sunset")
    frames = {}
    for shape in ("triangles", "rectangles"):
        page.execute_script("window.matspray.forceShape(arguments[0])", shape)
        assert page.execute_script("return window.matspray.drawnAs()")[1] == shape
        frames[shape] = frame(page)
    page.execute_script("window.matspray.forceShape(null)")
    drawn = np.abs(frames["rectangles"] - srgb_encode(BACKGROUND)).sum(-1) > 0.02
    assert drawn.mean() > 0.2 and np.abs(frames["triangles"] - frames["rectangles"]).max() <= 1 / 255 + 1e-9


@pytest.mark.slow
def test_another_light_changes_the_picture_and_a_dropped_exr_lights_as_the_packaged_one(site, page):
    run, _, _ = site
    camera = orbit(run)[0]
    names = page.execute_script("return window.matspray.lights()")
    assert len(names) == 11  # the estimated light, the 4 built-ins, the 6 packaged HDRIs
    frames = {name: show(page, camera, name) for name in names}
    city = frames["city"]
    inside = np.abs(city - srgb_encode(BACKGROUND)).sum(-1) > 0.02
    for a in names:  # every light lights the object, each its own way
        assert frames[a][inside].mean() > 0.02, a
        assert all(np.abs(frames[a] - frames[b])[inside].mean() > 0.005 for b in names if b != a), a
    hdri = Path(__file__).parents[1] / "matspray" / "hdri" / "city.exr"
    page.execute_script(
        "const bytes = Uint8Array.from(atob(arguments[0]), (c) => c.charCodeAt(0));"
        "const data = new DataTransfer(); data.items.add(new File([bytes], 'mine.exr'));"
        "document.body.dispatchEvent(new DragEvent('drop', {dataTransfer: data, bubbles: true}));",
        base64.b64encode(hdri.read_bytes()).decode(),
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and "mine.exr" not in page.execute_script("return window.matspray.lights()"):
        time.sleep(0.2)
    assert page.execute_script("return window.matspray.error") is None
    dropped = show(page, camera, "mine.exr")
    # three.js's EXR decoder against OpenEXR's, the page's area average against MatSpray's
    assert psnr_inside(dropped, city, inside) > 40


@pytest.mark.slow
def test_a_new_light_or_exposure_shades_the_same_g_buffer_again_and_a_turn_blends_a_new_one(site, page):
    camera = orbit(site[0])[0]
    sunset = show(page, camera, "sunset")
    blends = page.execute_script("return window.matspray.blends()")
    city = show(page, camera, "city")
    page.execute_script("window.matspray.setExposure(1)")
    brighter = frame(page)
    page.execute_script("window.matspray.setExposure(0)")
    assert page.execute_script("return window.matspray.blends()") == blends
    inside = np.abs(city - srgb_encode(BACKGROUND)).sum(-1) > 0.02
    assert np.abs(city - sunset)[inside].mean() > 0.005 and brighter[inside].mean() > city[inside].mean() + 0.02
    page.execute_script("window.matspray.setTurn(10)")
    assert page.execute_script("return window.matspray.blends()") == blends + 1
    controls = "return ['turn', 'exposure'].map((id) => Number(document.getElementById(id).value))"
    assert page.execute_script(controls) == [10, 0]  # the sliders show what a script set
    page.execute_script("window.matspray.setExposure(1)")
    assert page.execute_script(controls) == [10, 1]
    page.execute_script("window.matspray.setExposure(0)")


@pytest.mark.slow
def test_a_dropped_file_that_is_no_light_is_refused_in_one_line(site, page):
    page.execute_script(
        "const data = new DataTransfer(); data.items.add(new File([new Uint8Array(8)], 'notes.txt'));"
        "document.body.dispatchEvent(new DragEvent('drop', {dataTransfer: data, bubbles: true}));"
    )
    time.sleep(0.5)
    assert page.execute_script("return window.matspray.error") == "notes.txt: not an .hdr or .exr file"
    page.execute_script("window.matspray.error = null")


def drawn_in_blocks(image: np.ndarray, size: int) -> bool:  # [H, W, 3]: every size x size block one colour
    h, w = (image.shape[0] // size) * size, (image.shape[1] // size) * size
    blocks = image[:h, :w].reshape(h // size, size, w // size, size, 3)
    return bool((blocks == blocks[:, :1, :, :1]).all())


@pytest.mark.slow
def test_frames_per_second_at_512_pixels(site, page, tmp_path, record_property):
    """Frames of the page's own 512 x 512 view of 4 000 Gaussians (a sphere of disks about as dense as a trained
    asset's surface: each pixel under ~20 footprints), turned a little each (sorting and shading included), each
    waited for, timed after two frames of warm-up (`benchmarks.web_fps`): still (full size) and moving (as while the
    view is dragged: blended at half the width and height, each pixel filling 2 x 2 of the canvas). The issue's
    target is 5 frames per second; what this machine gives is printed and recorded (docs/dev/web.md)."""
    write_disk_sphere_page(tmp_path, 4000)
    try:
        open_page(page, tmp_path)
        assert page.execute_script("return document.getElementById('view').width") == 512
        still = milliseconds_per_frame(page)
        assert not drawn_in_blocks(frame(page), 2)
        moving = milliseconds_per_frame(page, moving=True)
        moving_frame = frame(page)
    finally:
        open_page(page, site[1])  # the module's page again, for any test after this one
    record_property("web_fps_512", 1000 / still)
    record_property("web_fps_512_moving", 1000 / moving)
    print(f"\npage at 512 x 512, 4 000 Gaussians: {still:.0f} ms a frame still, {moving:.0f} ms moving")
    assert (np.abs(moving_frame - srgb_encode(BACKGROUND)).sum(-1) > 0.02).mean() > 0.2  # the object
    assert drawn_in_blocks(moving_frame, 2)
    assert 1000 / still >= MIN_FPS and 1000 / moving >= MIN_MOVING_FPS, (still, moving)


MIN_FPS = 1.0  # still, 4 000 Gaussians: measured 3.1-5.2 on 2 loaded cores (docs/dev/web.md)
MIN_MOVING_FPS = 4.0  # moving: measured 8.5-13.4 there; a full-size frame (the old page's only kind) 3.1-5.8


# the moving frame's shaded target (the blended size, rows from the bottom) as RGBA bytes
SHADED_PIXELS = """
const v = window.matspray.viewer, t = v.target.shaded, out = new Uint8Array(4 * t.width * t.height);
v.renderer.readRenderTargetPixels(t, 0, 0, t.width, t.height, out);
return Array.from(out);
"""


@pytest.mark.slow
def test_a_drag_draws_small_frames_and_letting_go_a_full_one(site, page):
    def drag(script):
        page.execute_script(script)
        time.sleep(0.3)  # the frame is drawn on the next animation frame
        return frame(page)

    canvas = "document.getElementById('view')"
    page.execute_script("window.matspray.setTurn(0)")
    assert not drawn_in_blocks(frame(page), 2)
    dragged = drag(
        f"{canvas}.dispatchEvent(new PointerEvent('pointerdown', {{clientX: 10, bubbles: true}}));"
        "window.dispatchEvent(new PointerEvent('pointermove', {clientX: 40}));"
    )
    assert page.execute_script("return window.matspray.moving()") and drawn_in_blocks(dragged, 2)
    # shaded once per blended pixel, at the blended size, then enlarged: each 2 x 2 block is that pixel's bytes
    shaded = np.array(page.execute_script(SHADED_PIXELS), dtype=np.float64).reshape(256, 256, 4)[::-1, :, :3] / 255
    assert np.array_equal(dragged[::2, ::2], shaded)
    released = drag("window.dispatchEvent(new PointerEvent('pointerup', {}));")
    assert not page.execute_script("return window.matspray.moving()") and not drawn_in_blocks(released, 2)
    inside = np.abs(released - srgb_encode(BACKGROUND)).sum(-1) > 0.02
    assert inside.mean() > 0.2 and psnr_inside(dragged, released, inside) > 15  # the same view, coarser
    # while dragged a Gaussian blends nothing below alpha 1/32 (1/255 once let go): the faint rim goes
    background = np.round(released[0, 0] * 255)
    touched = [(np.abs(np.round(f * 255) - background).max(-1) > 1).mean() for f in (released, dragged)]
    print(f"\npixels the Gaussians touch: {touched[0]:.3f} let go, {touched[1]:.3f} dragged")
    assert touched[1] < 0.93 * touched[0], touched
