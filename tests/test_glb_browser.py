"""The exported glb in a real browser: Google's model-viewer (npm, installed by the Makefile into the venv)
in headless chromium loads it, and the object covers the pixels the Gaussian asset itself covers from the
same camera. Skipped, with the reason, where chromium, its driver, selenium or model-viewer are missing."""

import functools
import io
import math
import shutil
import sys
import threading
import time
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("trimesh")
pytest.importorskip("xatlas")
pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")
pytest.importorskip("PIL")

from matspray.cli import main  # noqa: E402
from matspray.data import Camera  # noqa: E402
from matspray.export.frames import GLTF_FROM_DATASET  # noqa: E402
from matspray.method.asset import read_asset  # noqa: E402
from matspray.render.raster.rasterize import rasterize  # noqa: E402
from tests.browser import headless_chromium  # noqa: E402
from tests.browser import missing_browser as missing_chromium  # noqa: E402
from tests.test_export import SMALL, make_disk_run  # noqa: E402

MODEL_VIEWER = Path(sys.prefix) / "node" / "node_modules" / "@google" / "model-viewer" / "dist" / "model-viewer.min.js"
SIZE = 160  # CSS pixels of the square viewer (device scale 1)
ORBIT = (
    35.0,
    70.0,
    4.5,
)  # model-viewer camera orbit: azimuth about +Y from +Z (deg), polar angle from +Y (deg), radius
FOV = 40.0  # vertical field of view, degrees
BACKGROUND = (255, 0, 255)  # a colour the object never takes: every other pixel is the object

PAGE = """<!doctype html><html><head><meta charset="utf-8">
<style>html, body {{ margin: 0; background: rgb{background}; }} \
model-viewer {{ width: {size}px; height: {size}px; display: block;
--poster-color: transparent; background-color: rgb{background}; }}</style></head><body>
<model-viewer id="mv" src="{src}" camera-target="0m 0m 0m" camera-orbit="{theta}deg {phi}deg {radius}m" \
field-of-view="{fov}deg"
 min-camera-orbit="auto auto 0m" max-camera-orbit="auto auto 100m" min-field-of-view="1deg" max-field-of-view="{fov}deg"
 interaction-prompt="none" shadow-intensity="0" exposure="1"></model-viewer>
<script>
window.viewerLoaded = false; window.viewerError = null;
const mv = document.getElementById('mv');
mv.addEventListener('load', () => {{ window.viewerLoaded = true; }});
mv.addEventListener('error', (e) => {{ window.viewerError = String(e.detail && e.detail.type || 'error'); }});
</script><script type="module" src="model-viewer.min.js"></script></body></html>"""


def missing_browser() -> str | None:
    """Why the browser test cannot run here, or None."""
    reason = f"model-viewer is not installed at {MODEL_VIEWER} (`make setup` installs it with npm, best effort)"
    return missing_chromium({MODEL_VIEWER: reason})


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A folder with the disk sphere's export (glTF frame), model-viewer and the page, served over http on a
    free port: (base url, run folder)."""
    reason = missing_browser()
    if reason is not None:
        pytest.skip(reason)
    root = tmp_path_factory.mktemp("browser")
    run = make_disk_run(root)
    site = root / "site"
    assert main(["export", "--run", str(run), "--out", str(site / "disks.glb"), *SMALL]) == 0
    shutil.copy(MODEL_VIEWER, site / "model-viewer.min.js")
    theta, phi, radius = ORBIT
    (site / "index.html").write_text(
        PAGE.format(src="disks.glb", size=SIZE, background=BACKGROUND, theta=theta, phi=phi, radius=radius, fov=FOV)
    )
    handler = functools.partial(QuietHandler, directory=str(site))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", run
    server.shutdown()
    server.server_close()


class QuietHandler(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map, ".glb": "model/gltf-binary", ".js": "text/javascript"}

    def log_message(self, *args):  # keep pytest's output clean
        pass


def browser():
    return headless_chromium(SIZE + 400, SIZE + 400)


def viewer_camera() -> Camera:
    """model-viewer's camera (orbit in glTF's Y-up frame) as a MatSpray camera in the dataset's frame."""
    theta, phi, radius = (math.radians(ORBIT[0]), math.radians(ORBIT[1]), ORBIT[2])
    eye_gltf = np.array(
        [radius * math.sin(phi) * math.sin(theta), radius * math.cos(phi), radius * math.sin(phi) * math.cos(theta)]
    )
    eye = np.linalg.inv(GLTF_FROM_DATASET[:3, :3]) @ eye_gltf
    fov_x = 2 * math.atan(math.tan(math.radians(FOV) / 2))  # square image: the same both ways
    return Camera.look_at(eye.tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], fov_x, SIZE, SIZE)


def coverage(png: bytes) -> np.ndarray:  # -> [H, W] bool: pixels that are not the background
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return np.abs(rgb - np.array(BACKGROUND)).sum(-1) > 30


@pytest.mark.slow
def test_model_viewer_loads_the_export_and_covers_the_assets_pixels(served):
    url, run = served
    driver = browser()
    try:
        driver.get(f"{url}/index.html")
        deadline, loaded = time.monotonic() + 60, False
        while time.monotonic() < deadline and not loaded:
            error = driver.execute_script("return window.viewerError")
            assert error is None, f"model-viewer failed to load the glb: {error}"
            loaded = bool(
                driver.execute_script(
                    "const mv = document.getElementById('mv'); return window.viewerLoaded && mv.loaded === true"
                )
            )
            time.sleep(0.2)
        assert loaded, "model-viewer did not fire `load` within 60 s"
        element = driver.find_element("id", "mv")
        seen = np.zeros((SIZE, SIZE), dtype=bool)
        for _ in range(50):  # the first frames after `load` may still be blank
            seen = coverage(element.screenshot_as_png)
            if seen.mean() > 0.02:
                break
            time.sleep(0.2)
    finally:
        driver.quit()
    asset = read_asset(run / "asset")
    with torch.no_grad():
        alpha = rasterize(asset.gaussians, viewer_camera(), torch.ones(len(asset.gaussians), 1)).alpha.numpy()
    expected = alpha >= 0.5
    assert seen.shape == expected.shape, (seen.shape, expected.shape)
    iou = (seen & expected).sum() / (seen | expected).sum()
    # the same object from the same camera: silhouettes agree but for antialiasing and the mesh's resolution
    assert expected.mean() > 0.1 and iou > 0.85, (
        f"browser coverage {seen.mean():.3f}, asset {expected.mean():.3f}, IoU {iou:.3f}"
    )
