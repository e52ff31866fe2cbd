"""Headless chromium for the browser tests: why one cannot run here, and a driver (the system's chromium and
chromedriver, software WebGL)."""

from __future__ import annotations

import shutil
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
DRIVER = Path("/usr/bin/chromedriver")


def missing_browser(needed: dict[Path, str] | None = None) -> str | None:
    """Why a browser test cannot run here, or None: selenium, chromium, its driver, then each of `needed`
    ({path: the reason when it is absent})."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (`make setup` installs it)"
    if not CHROMIUM.exists() and shutil.which("chromium") is None:
        return "chromium is not installed (`make setup` installs it, best effort)"
    if not DRIVER.exists():
        return f"chromedriver is not installed at {DRIVER}"
    return next((reason for path, reason in (needed or {}).items() if not path.exists()), None)


def headless_chromium(width: int, height: int):
    """A selenium driver of headless chromium with SwiftShader's WebGL, at device scale 1."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM if CHROMIUM.exists() else shutil.which("chromium"))
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        "--disable-gpu",
        "--force-device-scale-factor=1",
        f"--window-size={width},{height}",
    ):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(str(DRIVER)), options=options)  # the explicit driver: no network lookup
