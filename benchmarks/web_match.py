"""The page of `matspray export --web` against `matspray relight` on a run's own asset: the run's orbit at the page's
512 x 512, under each light, PSNR of the 8-bit sRGB frames over the pixels relight's object covers above 0.99 (the
issue's "inside the object"). relight renders the whole asset; the page draws what its export chose (`web.detail`,
`--web DIR DB`).

    python -m benchmarks.web_match --run RUN [--lights sunset city] [--frames 4] [--web-db DB]
"""

from __future__ import annotations

import argparse
import base64
import io
import math
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.web_fps import open_page


def frame(driver) -> np.ndarray:  # -> [H, W, 3] the canvas, sRGB in [0, 1]
    from PIL import Image

    url = driver.execute_script("return document.getElementById('view').toDataURL('image/png')")
    image = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
    return np.asarray(image).astype(np.float64) / 255


def show(driver, camera, light: str) -> np.ndarray:
    """The open page's frame of `camera` under the light named `light` ([H, W, 3] sRGB in [0, 1])."""
    K = [float(camera.K[0, 0]), float(camera.K[1, 1]), float(camera.K[0, 2]), float(camera.K[1, 2])]
    driver.execute_script(
        "window.matspray.setLight(arguments[0]); window.matspray.setCamera(arguments[1], arguments[2], "
        "arguments[3], arguments[4]);",
        light,
        camera.viewmat.double().reshape(-1).tolist(),
        K,
        camera.width,
        camera.height,
    )
    return frame(driver)


def psnr_inside(a: np.ndarray, b: np.ndarray, inside: np.ndarray) -> float:
    return -10 * math.log10(max(((a - b)[inside] ** 2).mean(), 1e-12))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="run folder made by `matspray run`")
    parser.add_argument("--lights", nargs="+", default=["sunset", "city"], help="packaged lights to compare under")
    parser.add_argument("--frames", type=int, default=4, help="orbit frames")
    parser.add_argument("--web-db", help="the page's PSNR, export's --web DIR DB (default: its default)")
    args = parser.parse_args()
    from matspray.cli import main as matspray
    from matspray.cli.relight import relight_source
    from matspray.data.images import read_image
    from matspray.web.pack import LIGHT_HEIGHT, srgb_encode
    from matspray.web.page import PAGE_SIZE
    from tests.browser import headless_chromium

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        export = ["export", "--run", args.run, "--web", str(root / "page")]
        relight = ["relight", "--run", args.run, "--env", *args.lights, "--views", "orbit", "--frames"]
        relight += [str(args.frames), "--resolution", str(PAGE_SIZE), "--env-height", str(LIGHT_HEIGHT)]
        if matspray(export + ([args.web_db] if args.web_db else [])) != 0:
            raise SystemExit("the page could not be exported (the message above says why)")
        if matspray([*relight, "--out", str(root / "relit")]) != 0:
            raise SystemExit("relight failed (the message above says why)")
        cameras = [c for _, c in relight_source(Path(args.run), "orbit", None, args.frames, "cpu")[1]]
        driver = headless_chromium(1000, 800)
        driver.set_script_timeout(300)
        values = []
        try:
            open_page(driver, root / "page")
            for i, camera in enumerate(cameras):
                camera = camera.scaled(PAGE_SIZE / max(camera.width, camera.height))
                for light in args.lights:
                    rgb, alpha = read_image(root / "relit" / f"orbit_{i:03d}_{light}.png")
                    inside = alpha.numpy() > 0.99
                    value = psnr_inside(show(driver, camera, light), srgb_encode(rgb.numpy()), inside)
                    values.append(value)
                    print(f"orbit frame {i}, {light}: {value:.1f} dB inside the object", flush=True)
            status = driver.execute_script("return document.getElementById('status').textContent")
        finally:
            driver.quit()
    print(f"page against relight, {args.run} ({status}): {min(values):.1f}-{max(values):.1f} dB")


if __name__ == "__main__":
    main()
