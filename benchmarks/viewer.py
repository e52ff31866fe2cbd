"""How fast `matspray view` is: one still frame (256 x 256, shading under an HDRI included), one frame while the camera
moves, and the time from `matspray view RUN` to the first picture in a (headless) browser.

    MATSPRAY_THREADS=2 python -m benchmarks.viewer [--run RUN] [--env HDRI] [--repeats 7]
                                                   [--screenshot docs/images/viewer.png]

Frame times are medians over --repeats renders of the demo asset through `Viewer.render` (what the page gets, PNG
encoding aside), on the CPU with the rasterizer `--backend auto` picks, and the CPU threads of $MATSPRAY_THREADS.
The first-picture time starts the command as a user would, opens the page in headless chromium as soon as the server
answers, and stops at the first screenshot that shows the viewer's picture (its backdrop grey around the object).
The browser helpers here are also what tests/test_view_browser.py drives the page with.
"""

from __future__ import annotations

import argparse
import io
import os
import shutil
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
# software WebGL: headless chromium renders viser's three.js page without a GPU
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-gpu-sandbox",
)
BACKDROP_SRGB = 63  # the viewer's backdrop (linear 0.05) as 8-bit sRGB


# ------------------------------------------------------------------------------------------ browser helpers
def chromium_missing() -> str | None:
    """Why a headless chromium cannot be driven here, or None when it can."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install 'matspray[test]')"
    chromium = shutil.which("chromium") or (CHROMIUM if Path(CHROMIUM).exists() else None)
    driver = shutil.which("chromedriver") or (CHROMEDRIVER if Path(CHROMEDRIVER).exists() else None)
    if chromium is None or driver is None:
        return (
            "chromium and chromium-driver are not installed "
            "(make setup installs them: apt-get install chromium chromium-driver)"
        )
    return None


def open_chromium(width: int = 1200, height: int = 700):
    """A headless chromium through selenium, with the system driver given explicitly: selenium's own driver manager
    would try the network (and send usage statistics)."""
    os.environ.setdefault("SE_AVOID_STATS", "true")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for flag in (*CHROMIUM_FLAGS, f"--window-size={width},{height}"):
        options.add_argument(flag)
    options.binary_location = shutil.which("chromium") or CHROMIUM
    return webdriver.Chrome(service=Service(shutil.which("chromedriver") or CHROMEDRIVER), options=options)


def page_image(driver) -> np.ndarray:  # -> [H, W, 3] uint8, the visible page
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))


def shows_picture(image: np.ndarray, share: float = 0.15) -> bool:
    """True when the page shows a viewer picture: at least `share` of the canvas is the viewer's backdrop grey (viser's
    empty page is white or black, never that grey)."""
    close = (np.abs(image.astype(int) - BACKDROP_SRGB) <= 3).all(-1)
    return float(close.mean()) >= share


def open_when_up(driver, url: str, timeout: float) -> None:
    """Load `url`, retrying while the server does not answer yet."""
    from selenium.common.exceptions import WebDriverException

    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((url.split("//")[1].split(":")[0], int(url.rsplit(":", 1)[1])), timeout=0.5):
                break
        except OSError:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{url} did not answer within {timeout:.0f} s") from None
            time.sleep(0.05)
    try:
        driver.get(url)
    except WebDriverException:
        time.sleep(0.2)
        driver.get(url)


def wait_for_text(driver, text: str, timeout: float) -> None:
    from selenium.webdriver.common.by import By

    deadline = time.monotonic() + timeout
    while text not in driver.find_element(By.TAG_NAME, "body").text:
        if time.monotonic() > deadline:
            raise TimeoutError(f"the page did not say {text!r} within {timeout:.0f} s")
        time.sleep(0.1)


def dismiss_notices(driver) -> None:
    """Close the page's notifications (headless chromium gets viser's "software WebGL" notice) for a clean
    screenshot."""
    from selenium.webdriver.common.by import By

    for button in driver.find_elements(By.CSS_SELECTOR, "[class*=Notification] button"):
        try:
            button.click()
        except Exception:  # noqa: BLE001 - a notice that closed by itself meanwhile
            pass


def save_screenshot(image: np.ndarray, path: Path, max_bytes: int = 300_000) -> Path:
    """The page as a PNG small enough for the docs (palette-quantised when the plain PNG is too large)."""
    from PIL import Image

    picture = Image.fromarray(image)
    path.parent.mkdir(parents=True, exist_ok=True)
    picture.save(path, optimize=True)
    if path.stat().st_size > max_bytes:
        picture.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path


# ------------------------------------------------------------------------------------------ measurements
def demo_run() -> Path | None:
    runs = sorted(p.parent for p in (ROOT / "runs").glob("*/objects/*/runs/*/dataset.json"))
    runs = [r for r in runs if (r / "asset" / "asset.ply").exists()]
    return runs[0] if runs else None


def frame_times(run: Path, env: str | None, repeats: int, size: int, backend: str = "auto") -> dict:
    import torch

    from matspray.data.camera import Camera
    from matspray.method.relight import render_gbuffer
    from matspray.render.backend import compute_target, rendering_with
    from matspray.render.shade.lights import hdri_files
    from matspray.view.frames import progressive_size
    from matspray.view.server import Viewer, ViewerConfig

    device, backend = compute_target("cpu", backend)
    shared = hdri_files()
    env = env or (str(next(iter(shared.values()))) if shared else "sunset")
    viewer = Viewer(
        run,
        ViewerConfig(env=(env,) if Path(env).exists() else ()),
        device=device,
        backend=backend,
        notify=lambda _: None,
    )
    label = Path(env).name if Path(env).exists() else env
    assert viewer.set_light(label), f"could not load {env}"
    start = viewer.start_camera
    results = {
        "threads": torch.get_num_threads(),
        "backend": backend,
        "light": label,
        "gaussians": len(viewer.run.asset(viewer.state.variant).gaussians),
    }
    for name, (width, height) in (("still", (size, size)), ("moving", progressive_size(1.0, size, moving=True))):
        camera = Camera.look_at(
            start.center,
            torch.tensor(viewer.run.object_frame(viewer.state.variant)[0]),
            (0.0, 0.0, 1.0),
            0.7,
            width,
            height,
        )
        viewer.render(camera)  # warm-up: kernels, caches
        times, raster = [], []
        for _ in range(repeats):
            times.append(viewer.render(camera).seconds)
            t0 = time.perf_counter()
            with torch.no_grad(), rendering_with(backend):
                render_gbuffer(viewer.run.asset(viewer.state.variant), camera)
            raster.append(time.perf_counter() - t0)
        results[name] = {
            "size": f"{width}x{height}",
            "median_ms": 1000 * statistics.median(times),
            "min_ms": 1000 * min(times),
            "rasterize_ms": 1000 * statistics.median(raster),
        }
    viewer.stop()
    return results


def first_picture(run: Path, port: int, timeout: float, screenshot: Path | None, backend: str = "auto") -> float:
    """Seconds from starting `matspray view RUN` to the first screenshot showing the viewer's picture."""
    driver = open_chromium(1200, 820)  # started first: a user's browser is open already
    url = f"http://127.0.0.1:{port}"
    start = time.monotonic()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "matspray",
            "view",
            str(run),
            "--port",
            str(port),
            "--device",
            "cpu",
            "--backend",
            backend,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        open_when_up(driver, url, timeout)
        while not shows_picture(page_image(driver)):
            if time.monotonic() - start > timeout or process.poll() is not None:
                raise TimeoutError(f"no picture within {timeout:.0f} s (viewer exit status {process.poll()})")
            time.sleep(0.05)
        seconds = time.monotonic() - start
        if screenshot is not None:
            wait_for_text(driver, "still: full resolution", timeout)  # the full-size frame after the first, small one
            dismiss_notices(driver)
            time.sleep(1.0)
            save_screenshot(page_image(driver), screenshot)
        return seconds
    finally:
        driver.quit()
        process.terminate()
        process.wait(timeout=20)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, help="run folder with an asset (default: the first demo run under runs/)")
    parser.add_argument("--env", help="HDRI to shade under (default: the first file of shared/data/hdri, else sunset)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--size", type=int, default=256, help="still frame: size x size pixels (default 256)")
    parser.add_argument("--backend", default="auto", help="rasterizer, as `matspray view --backend` (default auto)")
    parser.add_argument("--port", type=int, default=8097)
    parser.add_argument("--timeout", type=float, default=120.0)
    parser.add_argument("--no-browser", action="store_true", help="frame times only")
    parser.add_argument("--screenshot", type=Path, help="also save the page a few seconds after the first picture")
    args = parser.parse_args(argv)
    run = args.run or demo_run()
    if run is None:
        print("no run with an asset under runs/; pass --run RUN", file=sys.stderr)
        return 2
    times = frame_times(run, args.env, args.repeats, args.size, args.backend)
    print(
        f"viewer frame times: {run}, {times['gaussians']} Gaussians, light {times['light']}, "
        f"backend {times['backend']}, "
        f"{times['threads']} CPU threads (median of {args.repeats})"
    )
    for name, target in (("still", 150), ("moving", 50)):
        t = times[name]
        print(
            f"  {name:6s} {t['size']:>8s}: {t['median_ms']:7.1f} ms (min {t['min_ms']:.1f}; "
            f"rasterizing alone {t['rasterize_ms']:.1f}) "
            f"target <= {target} ms"
        )
    if not args.no_browser:
        missing = chromium_missing()
        if missing:
            print(f"  first picture: not measured ({missing})")
        else:
            seconds = first_picture(run, args.port, args.timeout, args.screenshot, args.backend)
            print(f"  `matspray view RUN` to the first picture in headless chromium: {seconds:.1f} s (target <= 5 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
