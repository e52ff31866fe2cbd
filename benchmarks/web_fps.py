"""Frames per second of `matspray export --web`'s page in headless chromium with software WebGL (SwiftShader), at
its 512 x 512 view: a sphere of COUNT flat Gaussians, as wide as keeps every pixel of it under the same number of
footprints at any count (sigma 0.05 at 4 000, about a trained surface's density), turned 3 degrees a frame (sorting
and shading included), each frame waited for, after two frames of warm-up. Each count is timed still (the full-size
frame drawn when the view stops) and moving (the smaller frames drawn while the view is dragged).

    python -m benchmarks.web_fps --gaussians 4000 40000
    python -m benchmarks.web_fps --gaussians 40000 --passes   # each pass of a frame timed on its own
    python -m benchmarks.web_fps --gaussians 40000 --shapes   # triangles against rectangles, interleaved
    python -m benchmarks.web_fps --scripts OLD.js NEW.js      # pages with these builds of the script, interleaved
    python -m benchmarks.web_fps --run RUN                    # a run's asset (its `matspray export --web` page)
    python -m benchmarks.web_fps --run RUN --web-db 35 32 29  # its pages exported at these PSNRs, interleaved

Besides the wall time, each frame's CPU time: the seconds that chromium's processes (SwiftShader's threads among
them) spent, which other work on the machine's cores changes far less than the wall time.
"""

from __future__ import annotations

import argparse
import functools
import os
import shutil
import tempfile
import time
from pathlib import Path

import torch

WARM_UP, FRAMES, STEP = 2, 5, 3.0


def write_disk_sphere_page(folder, count: int) -> None:
    """The page of `count` flat disks on the unit sphere (the tests' disk sphere, thinner as it gets denser)."""
    from matspray.method.asset import Asset
    from matspray.method.relight import orbit_spec
    from matspray.web.page import write_page
    from tests.scenes import sky_map, sphere_cameras, sphere_of_disks

    g, normals, materials = sphere_of_disks(count)
    sigma = 0.05 * (4000 / count) ** 0.5
    g.log_scales = torch.tensor([sigma, sigma, 0.003]).log().expand(count, 3).clone()
    spec = orbit_spec(sphere_cameras(6, 64), torch.zeros(3), (0.0, 0.0, 1.0))
    write_page(folder, Asset(g, materials, normals), spec, sky_map())


def open_page(driver, folder: Path, timeout: float = 120.0, hooks: bool = True) -> None:
    """Open the page in `folder` from file:// (no server), with its test hooks (`?test`: the page's src/hooks.js)
    unless `hooks` is False, and wait until it has started."""
    driver.get((Path(folder) / "index.html").as_uri() + ("?test" if hooks else ""))
    deadline, state = time.monotonic() + timeout, None
    while time.monotonic() < deadline:
        state = driver.execute_script("return window.matspray && [window.matspray.ready, window.matspray.error]")
        if state and (state[0] or state[1]):
            break
        time.sleep(0.1)
    if not (state and state[0]):
        raise RuntimeError(f"the page did not start: {state}")


def milliseconds_per_frame(driver, moving: bool = False) -> float:
    """The open page's frame time, after WARM_UP frames: full size, or as drawn while the view is dragged."""
    return frame_cost(driver, moving)[0]


def frame_cost(driver, moving: bool = False) -> tuple[float, float]:
    """(wall, CPU) milliseconds per frame of the open page, after WARM_UP frames (milliseconds_per_frame)."""
    flag = "true" if moving else "false"
    driver.execute_script(f"return window.matspray.timeFrames({WARM_UP}, {STEP}, {flag})")
    before = chromium_cpu_seconds(driver)
    wall = driver.execute_script(f"return window.matspray.timeFrames({FRAMES}, {STEP}, {flag})")
    return wall, (chromium_cpu_seconds(driver) - before) * 1000 / FRAMES


def chromium_cpu_seconds(driver) -> float:
    """User and system seconds of the driver's chromedriver and every process under it (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            children.setdefault(int(fields[1]), []).append(int(entry))
    total, todo = 0, [driver.service.process.pid]
    while todo:
        pid = todo.pop()
        todo += children.get(pid, [])
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


# each pass of the page's frame drawn and waited for on its own (a pixel of the canvas read back), still and moving;
# "splats, hidden": the splat pass with every rectangle shrunk to nothing on screen (vertices and set-up only)
PASSES = """
const v = window.matspray.viewer, r = v.renderer, gl = r.getContext(), px = new Uint8Array(4);
const sync = () => { r.setRenderTarget(null); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); };
const time = (f) => { sync(); const s = performance.now(); for (let i = 0; i < 3; i++) { f(); sync(); }
  return Math.round((performance.now() - s) / 3); };
const out = {}, u = v.splatUniforms;
for (const moving of [false, true]) {
  v.moving = moving; v.render();
  const into = (target, scene) => () => { r.setRenderTarget(target); r.render(scene, v.camera); };
  const splats = () => { r.setRenderTarget(v.target); r.clear(true, false, false); r.render(v.shape.scene, v.camera); };
  const size = u.size.value.clone();
  const hidden = () => { u.size.value.set(1e9, 1e9); splats(); u.size.value.copy(size); };
  out[moving ? "moving" : "still"] = {
    frame: time(() => { v.turn += 3; v.render(); }), project: time(into(v.projectTarget, v.projectScene)),
    splats: time(splats), "splats, hidden": time(hidden), shade: time(() => v.shade()) };
}
v.moving = false;
return out;
"""


def export_run_page(folder: Path, run: str, web_db: str | None = None) -> None:
    """The page of a run folder's default asset, as `matspray export --web DIR [DB]` writes it."""
    from matspray.cli import main as matspray

    if matspray(["export", "--run", run, "--web", str(folder), *([web_db] if web_db else [])]) != 0:
        raise SystemExit(f"{run}: its page could not be exported (the message above says why)")


def run_pages(root: Path, run: str, dbs: list[str]) -> list[tuple[str, Path]]:
    """The pages of a run's asset exported at each of the PSNRs `dbs`, under `root`: (name, folder)."""
    folders = []
    for k, db in enumerate(dbs):
        export_run_page(root / f"page{k}", run, db)
        folders.append((f"--web DIR {db}", root / f"page{k}"))
    return folders


def pages(root: Path, write_page, scripts: list[str]) -> list[tuple[str, Path]]:
    """The page `write_page(folder)` makes, under `root`, one copy per script in `scripts` (or the built one):
    (name, folder)."""
    write_page(root / "page")
    if not scripts:
        return [("page", root / "page")]
    folders = []
    for k, script in enumerate(scripts):
        folder = root / f"page{k}"
        shutil.copytree(root / "page", folder)
        shutil.copyfile(script, folder / "matspray-web.js")
        folders.append((script, folder))
    return folders


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[4000, 40000])
    parser.add_argument("--run", help="time the page of this run folder's asset instead of the disk spheres")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--passes", action="store_true", help="time each pass of a frame instead")
    parser.add_argument("--shapes", action="store_true", help="time each Gaussian drawn in a triangle, a rectangle")
    parser.add_argument("--scripts", nargs="+", default=[], help="builds of the page's script to time, interleaved")
    parser.add_argument("--web-db", nargs="+", default=[], help="with --run: its pages at these PSNRs, interleaved")
    args = parser.parse_args()
    if args.web_db and (not args.run or args.scripts):
        parser.error("--web-db times the pages of --run's asset, with the built script (not with --scripts)")
    from tests.browser import headless_chromium

    driver = headless_chromium(1000, 800)
    driver.set_script_timeout(600)
    try:
        subjects = [(f"{n} Gaussians", functools.partial(write_disk_sphere_page, count=n)) for n in args.gaussians]
        if args.run:
            subjects = [(f"the asset of {args.run}", functools.partial(export_run_page, run=args.run))]
        for label, write_page in subjects:
            with tempfile.TemporaryDirectory() as tmp:
                if args.web_db:
                    folders = run_pages(Path(tmp), args.run, args.web_db)
                else:
                    folders = pages(Path(tmp), write_page, args.scripts)
                open_page(driver, folders[0][1])
                if args.passes:
                    for _ in range(args.repeats):
                        print(f"{label}, ms a pass: {driver.execute_script(PASSES)}", flush=True)
                    continue
                for shape in ("rectangles", "triangles") * args.repeats if args.shapes else ():
                    driver.execute_script("window.matspray.forceShape(arguments[0])", shape)
                    still, moving = milliseconds_per_frame(driver), milliseconds_per_frame(driver, True)
                    print(f"{label} as {shape}: {still:.0f} ms still, {moving:.0f} ms moving", flush=True)
                if args.shapes:
                    continue
                times = {name: [] for name, _ in folders}
                for _ in range(args.repeats):
                    for name, folder in folders:
                        open_page(driver, folder)
                        times[name].append((frame_cost(driver), frame_cost(driver, True)))
            for name, costs in times.items():
                for k, state in enumerate(("still", "moving")):
                    pairs = [t[k] for t in costs]
                    shown = ", ".join(f"{w:.0f} ms ({1000 / w:.1f} fps, CPU {c:.0f} ms)" for w, c in pairs)
                    print(f"{label} at 512 x 512, {name}, {state}: {shown}", flush=True)
    finally:
        driver.quit()


if __name__ == "__main__":
    main()
