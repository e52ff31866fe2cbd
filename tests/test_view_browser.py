"""`matspray view` in a real browser: the server runs in this process on a free port, headless chromium (software
WebGL) opens the page through selenium, and the test looks at screenshots. Skips with the reason when chromium, its
driver or selenium are missing (`make setup` installs them as best effort).

Set MATSPRAY_VIEWER_SCREENSHOT=PATH to keep the page's screenshot (docs/images/viewer.png is one, of the demo run,
taken by the same helpers through `python -m benchmarks.viewer --screenshot`)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.viewer import chromium_missing, open_chromium, page_image, save_screenshot, shows_picture
from tests.test_view import make_view_run
from tests.viewer_process import free_port

pytest.importorskip("viser")
MISSING = chromium_missing()
pytestmark = [pytest.mark.slow, pytest.mark.skipif(MISSING is not None, reason=f"no headless browser: {MISSING}")]
WINDOW = (1200, 700)
PANEL = 360  # viser's control panel covers this many pixels at the right of the page
NOTICE = (330, 170)  # and its "software WebGL" notice this corner at the top left


def wait_for(condition, timeout: float = 60.0, every: float = 0.1, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    """(viewer, driver): a viewer of the disk sphere's run, opened in headless chromium."""
    from matspray.view.server import Viewer, ViewerConfig

    run = make_view_run(tmp_path_factory.mktemp("browser"), gaussians=1500)
    try:  # an exported mesh beside the asset, as `matspray export --out RUN/export/NAME.glb` leaves one
        import trimesh

        (run / "export").mkdir()
        trimesh.creation.icosphere(subdivisions=2).export(run / "export" / "sphere.glb")
    except ImportError:
        pass
    told = []
    viewer = Viewer(
        run,
        ViewerConfig(port=free_port(), resolution=160, settle=0.15),
        device="cpu",
        backend="torch",
        notify=told.append,
    )
    viewer.told = told
    url = viewer.start()
    driver = open_chromium(*WINDOW)
    try:
        driver.get(url.replace("localhost", "127.0.0.1"))
        yield viewer, driver
    finally:
        driver.quit()
        viewer.stop()


def full_frame(viewer, after=None, timeout: float = 60.0):
    """The tab's latest full-size frame once there is one (newer than `after`)."""

    def ready():
        views = list(viewer.views.values())
        if not views:
            return None
        view = views[0]
        frame = view.last_frame
        still = view.progressive.shown == "full" and not view.progressive.pending
        if frame is None or not still or frame is after or max(frame.size) != viewer.state.resolution:
            return None
        return frame

    return wait_for(ready, timeout=timeout, what="a full-size frame")


def object_mask(frame, shape) -> np.ndarray:
    """Where the asset covers the page: the frame's alpha stretched to the canvas (the page shows the frame full size),
    without its edge, the control panel and the notice corner."""
    height, width = shape[:2]
    alpha = frame.alpha.numpy()
    rows = np.minimum((np.arange(height) + 0.5) * alpha.shape[0] / height, alpha.shape[0] - 1).astype(int)
    cols = np.minimum((np.arange(width) + 0.5) * alpha.shape[1] / width, alpha.shape[1] - 1).astype(int)
    inside = alpha > 0.99
    inside[1:-1, 1:-1] &= (
        inside[:-2, 1:-1] & inside[2:, 1:-1] & inside[1:-1, :-2] & inside[1:-1, 2:]
    )  # one pixel in from the edge
    mask = inside[rows][:, cols]
    mask[:, width - PANEL :] = False
    mask[: NOTICE[1], : NOTICE[0]] = False
    return mask


def stretched(frame, shape) -> np.ndarray:  # the frame's image at the page's size (nearest)
    height, width = shape[:2]
    rows = np.minimum((np.arange(height) + 0.5) * frame.image.shape[0] / height, frame.image.shape[0] - 1).astype(int)
    cols = np.minimum((np.arange(width) + 0.5) * frame.image.shape[1] / width, frame.image.shape[1] - 1).astype(int)
    return frame.image[rows][:, cols]


def settled(viewer, driver, after=None):
    """(frame, page image) once the page shows the tab's latest full-size frame (newer than `after`): the object's
    pixels within a few levels of the frame's. The frame is read again at every try: the camera may still move."""
    errors = []

    def matches():
        frame = full_frame(viewer, after)
        image = page_image(driver)
        mask = object_mask(frame, image.shape)
        errors.append(np.abs(image[mask].astype(float) - stretched(frame, image.shape)[mask]).mean())
        return (
            (frame, image) if errors[-1] < 12 and frame is viewer.views[next(iter(viewer.views))].last_frame else None
        )

    try:
        return wait_for(matches, what="the page to show the frame", every=0.3)
    except AssertionError:
        raise AssertionError(f"the page did not show the frame: mean differences {errors[-3:]}") from None


def test_the_page_shows_the_rendered_object(page):
    viewer, driver = page
    frame, image = settled(viewer, driver)
    mask = object_mask(frame, image.shape)
    assert mask.sum() > 2000  # the sphere covers a good part of the visible page
    assert shows_picture(image[:, : image.shape[1] - PANEL])  # backdrop around it
    assert np.abs(image[mask].astype(float).mean(0) - 63).max() > 15  # the object is not the backdrop
    assert image[mask].astype(float).std() > 5  # and is shaded, not flat
    if os.environ.get("MATSPRAY_VIEWER_SCREENSHOT"):
        save_screenshot(image, Path(os.environ["MATSPRAY_VIEWER_SCREENSHOT"]))


def choose(driver, label: str, option: str) -> None:
    """Pick `option` in the page's dropdown labelled `label`, as a person does: click it, click the entry."""
    from selenium.webdriver.common.by import By

    field = wait_for(
        lambda: next((el for el in driver.find_elements(By.TAG_NAME, "label") if el.text.strip() == label), None),
        timeout=30,
        what=f"the control {label!r}",
    )
    driver.find_element(By.ID, field.get_attribute("for")).click()
    entry = wait_for(
        lambda: next(
            (el for el in driver.find_elements(By.CSS_SELECTOR, "[role=option]") if el.text.strip() == option), None
        ),
        timeout=10,
        what=f"the entry {option!r}",
    )
    entry.click()


def test_changing_the_light_in_the_page_changes_the_picture(page):
    viewer, driver = page
    before, before_image = settled(viewer, driver)
    choose(driver, "light", "sunset")
    wait_for(lambda: viewer.state.light == "sunset", timeout=20, what="the light to change")
    after, after_image = settled(viewer, driver, after=before)
    mask = object_mask(after, after_image.shape) & object_mask(before, before_image.shape)
    assert np.abs(after_image[mask].astype(float) - before_image[mask].astype(float)).mean() > 8


def test_a_bad_upload_is_one_line_in_the_page_and_the_light_stays(page, tmp_path):
    from selenium.webdriver.common.by import By

    viewer, driver = page
    light = viewer.state.light
    bad = tmp_path / "not-a-light.exr"
    bad.write_bytes(b"this is no OpenEXR file")
    driver.find_element(By.CSS_SELECTOR, "input[type=file]").send_keys(str(bad))
    wait_for(
        lambda: "not-a-light.exr" in driver.find_element(By.TAG_NAME, "body").text, timeout=20, what="the notification"
    )
    assert viewer.state.light == light and any("not-a-light.exr" in line and "\n" not in line for line in viewer.told)


def test_an_uploaded_hdri_becomes_the_light(page, tmp_path):
    from selenium.webdriver.common.by import By

    from matspray.data.images import write_image
    from tests.scenes import sky_map

    viewer, driver = page
    good = tmp_path / "my sky.exr"
    write_image(good, sky_map(32) * torch.tensor([1.0, 0.6, 0.3]))
    driver.find_element(By.CSS_SELECTOR, "input[type=file]").send_keys(str(good))
    wait_for(lambda: viewer.state.light == "my sky.exr", timeout=20, what="the uploaded light")
    assert "my sky.exr" in [c.label for c in viewer.choices]


def test_the_snapshot_button_writes_a_png_into_the_run(page):
    from selenium.webdriver.common.by import By

    viewer, driver = page
    folder = viewer.run.root / "view"

    def snapshot_button():  # the page may still be building its controls when this test runs first
        return next(
            (el for el in driver.find_elements(By.TAG_NAME, "button") if el.text.strip().startswith("snapshot")), None
        )

    wait_for(snapshot_button, timeout=30, what="the snapshot button").click()

    def written():  # the snapshot itself, not the temporary file it is written to first
        return [p for p in folder.glob("*.png") if not p.name.startswith(".")] if folder.exists() else None

    files = wait_for(written, timeout=30, what="the snapshot file")
    assert len(files) == 1 and files[0].stat().st_size > 1000
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_the_exported_glb_is_shown_beside_or_instead_of_the_gaussians(page):
    pytest.importorskip("trimesh")  # the fixture writes the glb with it
    from selenium.webdriver.common.by import By

    viewer, driver = page
    # trimesh is here, so the fixture wrote RUN/export/sphere.glb: the viewer must have found it (no skip: a viewer
    # that missed it would pass unseen)
    assert [p.name for p in viewer.run.glbs] == ["sphere.glb"]
    choose(driver, "glb", "beside")
    wait_for(lambda: viewer.state.glb == "beside" and viewer.gui.mesh is not None, timeout=20, what="the glb beside")
    assert full_frame(viewer) is not None  # the Gaussians are still drawn by MatSpray
    choose(driver, "glb", "instead")
    wait_for(
        lambda: "glb shown instead" in driver.find_element(By.TAG_NAME, "body").text,
        timeout=20,
        what="the Gaussians hidden",
    )
    assert viewer.gui.mesh is not None
    choose(driver, "glb", "hidden")
    wait_for(lambda: viewer.state.glb == "hidden" and viewer.gui.mesh is None, timeout=20, what="the glb hidden")


def test_a_tab_that_opened_the_page_before_the_run_loaded_gets_one_view_and_its_picture(tmp_path):
    """`matspray view` serves the page first (launch.open_page) and attaches the viewer when the run is loaded: a tab
    connected meanwhile is served then, once, however viser reports it."""
    from matspray.view.launch import LOADING, open_page
    from matspray.view.server import Viewer, ViewerConfig

    run = make_view_run(tmp_path, gaussians=800)
    page = open_page("127.0.0.1", free_port())
    driver = open_chromium(*WINDOW)
    viewer = None
    try:
        driver.get(page.url.replace("localhost", "127.0.0.1"))
        wait_for(lambda: page.server.get_clients() or None, what="the tab to connect")
        assert LOADING.split("**")[-1].strip() in driver.page_source  # the page says the run is loading
        viewer = Viewer(
            run,
            ViewerConfig(resolution=96, settle=0.1),
            device="cpu",
            backend="torch",
            notify=lambda _: None,
            page=page,
        )
        viewer.start()
        frame = full_frame(viewer)
        assert len(viewer.views) == 1 and frame is not None
        wait_for(lambda: shows_picture(page_image(driver)) or None, what="the picture in the page")
    finally:
        driver.quit()
        (viewer.stop() if viewer is not None else page.stop())
