"""The picture of `matspray export --web`'s page in docs/guide/export.md: a run's page (as export makes it by
default) in headless chromium, under one light, the whole window with its controls.

    python -m benchmarks.web_picture --run RUN [--light studio] [--turn 30] --out docs/images/web_page.png
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from benchmarks.web_fps import export_run_page, open_page


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="run folder made by `matspray run`")
    parser.add_argument("--light", default="studio", help="a light of the page's list")
    parser.add_argument("--turn", type=float, default=0.0, help="degrees along the orbit")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    from tests.browser import headless_chromium

    with tempfile.TemporaryDirectory() as tmp:
        export_run_page(Path(tmp) / "page", args.run)
        driver = headless_chromium(900, 700)
        try:
            open_page(driver, Path(tmp) / "page", hooks=False)
            driver.execute_script(
                "window.matspray.setLight(arguments[0]); window.matspray.setTurn(arguments[1]);", args.light, args.turn
            )
            driver.save_screenshot(str(args.out))
        finally:
            driver.quit()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
