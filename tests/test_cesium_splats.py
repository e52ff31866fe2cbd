"""The splats as CesiumJS draws them: `matspray export --splats FILE.glb` writes FILE_3dtiles/, a one-tile 3D Tiles
tileset whose glb holds the splats SPZ-compressed (KHR_gaussian_splatting_compression_spz_2, by gsply). Its SPZ
stream reads back to the splats within SPZ's steps; CesiumJS (npm `cesium`, installed by `make setup`) in headless
chromium loads the tileset and draws the splats. Skipped, with the reason, where gsply, chromium, its driver, selenium
or CesiumJS are missing."""

from __future__ import annotations

import base64
import functools
import io
import json
import sys
import threading
import time
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import torch

from matspray.gltf.splats import SPZ_EXTENSION, read_splats_glb
from tests.browser import headless_chromium, missing_browser
from tests.scenes import sky_map, sphere_cameras, sphere_of_disks

pytest.importorskip("gsply", reason="gsply (the SPZ writer, in the `export` extra) is not installed")

CESIUM = Path(sys.prefix) / "node" / "node_modules" / "cesium" / "Build" / "Cesium"
PAGE = """<!doctype html><html><head><meta charset="utf-8"><link href="Cesium/Widgets/widgets.css" rel="stylesheet">
<style>html, body, #c { margin: 0; width: 320px; height: 320px; overflow: hidden; }</style></head>
<body><div id="c"></div>
<script>window.CESIUM_BASE_URL = 'Cesium/'; window.state = {error: null, ready: false};</script>
<script src="Cesium/Cesium.js"></script>
<script>
(async () => {
  try {
    const viewer = new Cesium.Viewer('c', {baseLayer: false, baseLayerPicker: false, geocoder: false,
      homeButton: false, sceneModePicker: false, navigationHelpButton: false, animation: false, timeline: false,
      fullscreenButton: false, infoBox: false, selectionIndicator: false, globe: false, skyBox: false,
      skyAtmosphere: false, contextOptions: {webgl: {preserveDrawingBuffer: true}}});
    viewer.scene.backgroundColor = Cesium.Color.MAGENTA;
    const tileset = await Cesium.Cesium3DTileset.fromUrl('tiles/tileset.json');
    tileset.tileFailed.addEventListener((e) => { window.state.error = String(e.message); });
    viewer.scene.primitives.add(tileset);
    await viewer.zoomTo(tileset, new Cesium.HeadingPitchRange(0.5, -0.3, 4.5));
    Object.assign(window, {viewer, tileset});
    window.state.ready = true;
  } catch (e) { window.state.error = String(e && e.stack || e); }
})();
</script></body></html>"""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The disk sphere written by the library that `export --splats` calls (the command itself, from a run folder,
    is tests/test_splats_glb.py's): no run folder, dataset or visual hull to make first."""
    from matspray.export.splats import write_splats
    from matspray.method.asset import Asset
    from matspray.method.relight import orbit_spec
    from matspray.render.shade.envmap import EnvironmentMap

    root = tmp_path_factory.mktemp("cesium")
    light = EnvironmentMap.from_tensor(sky_map(), learnable=False)
    spec = orbit_spec(sphere_cameras(4, 32), torch.zeros(3), (0.0, 0.0, 1.0))
    g, normals, materials = sphere_of_disks(1500)
    written = write_splats(root / "disks.glb", Asset(g, materials, normals), light.prefilter(), light.map, spec)
    assert root / "disks_3dtiles" / "tileset.json" in written
    return root


def test_the_spz_tileset_holds_the_splats_within_spz_steps(exported):
    from gsply.spz import read_spz

    tiles = exported / "disks_3dtiles"
    tileset = json.loads((tiles / "tileset.json").read_text())
    assert SPZ_EXTENSION in tileset["extensions"]["3DTILES_content_gltf"]["extensionsRequired"]
    blob = (tiles / "splats.glb").read_bytes()
    length = int.from_bytes(blob[12:16], "little")
    document = json.loads(blob[20 : 20 + length])
    view = document["bufferViews"][0]
    spz_file = exported / "payload.spz"
    spz_file.write_bytes(blob[20 + length + 8 + view["byteOffset"] :][: view["byteLength"]])
    data = read_spz(spz_file)
    splats, _ = read_splats_glb(exported / "disks.glb")
    assert np.abs(data.means - splats.positions).max() <= 2.0**-12  # 12 fractional bits
    assert np.abs(data.sh0 - splats.sh[:, 0]).max() < 0.05  # 8-bit colour
    assert document["accessors"][0]["count"] == len(splats.positions) and "bufferView" not in document["accessors"][0]


class QuietHandler(SimpleHTTPRequestHandler):
    extensions_map = {**SimpleHTTPRequestHandler.extensions_map, ".glb": "model/gltf-binary", ".js": "text/javascript"}

    def log_message(self, *args):
        pass


@pytest.mark.slow
def test_cesium_loads_the_tileset_and_draws_the_splats(exported):
    """Served over http (CesiumJS starts web workers, which file:// pages may not); a sphere of splats fills its
    outline, where a point cloud of 1 500 points would leave most of it background."""
    from PIL import Image

    reason = missing_browser({CESIUM: f"CesiumJS is not installed at {CESIUM} (`make setup` installs npm's cesium)"})
    if reason is not None:
        pytest.skip(reason)
    site = exported / "site"
    site.mkdir()
    (site / "Cesium").symlink_to(CESIUM)
    (site / "tiles").symlink_to(exported / "disks_3dtiles")
    (site / "index.html").write_text(PAGE)
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(QuietHandler, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    driver = headless_chromium(400, 400)
    try:
        driver.get(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        deadline, state = time.monotonic() + 180, None
        while time.monotonic() < deadline:
            state = driver.execute_script(
                "return [window.state.ready && window.tileset.tilesLoaded, window.state.error]"
            )
            if state[0] or state[1]:
                break
            time.sleep(0.2)
        assert state == [True, None], f"CesiumJS did not load the tileset: {state}"
        deadline, drawn = time.monotonic() + 120, np.zeros((1, 1), dtype=bool)
        while time.monotonic() < deadline and drawn.mean() <= 0.05:  # sorted in a worker, drawn frames later
            time.sleep(0.25)
            url = driver.execute_script("window.viewer.render(); return window.viewer.canvas.toDataURL('image/png')")
            image = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
            drawn = np.abs(np.asarray(image).astype(int) - [255, 0, 255]).sum(-1) > 60
    finally:
        driver.quit()
        server.shutdown()
        server.server_close()
    rows, cols = np.nonzero(drawn)
    assert drawn.mean() > 0.05, drawn.mean()
    box = drawn[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
    assert box.mean() > 0.7, box.mean()  # a filled disc covers pi / 4 of its box
