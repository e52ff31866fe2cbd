"""A public clone: the repository's own files (tracked, and untracked ones git does not ignore) copied alone into a
temporary folder, no `../shared` beside it, run with nothing in the environment but PATH and a fresh HOME, and
without the network (a guard refuses any connection that leaves this machine). There, the commands a new user runs
first: `demo --preset test`, `info`, `run` on a capture-like dataset (photos and cameras only, no ground truth),
`eval` of that run with its default lights, `relight` under every named light, `view` starting and stopping,
`colmap --help`. Each must finish without an error or a traceback.

The compiled CPU kernels (numba's cache, in the __pycache__ folders beside their modules) are carried over when this
tree has them, as `make`'s install leaves them in a clone (it compiles them once); without them the first command
compiles them (70 s).
The demo and the run take fewer steps than the test preset's (`--set`), which changes no code path.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.scenes import capture_like
from tests.viewer_process import free_port, serve_then_interrupt

ROOT = Path(__file__).resolve().parents[1]
FEWER_STEPS = ["--set", "geometry.iterations=20", "refine.iterations=2", "refine.light_warmup=1"]

# Run as `python -c GUARD ARGS...`: the CLI, with every socket connection off this machine refused.
GUARD = """
import runpy, socket, sys
LOCAL = ("127.0.0.1", "::1", "localhost", "0.0.0.0")
_connect = socket.socket.connect
def connect(self, address):
    if self.family in (socket.AF_INET, socket.AF_INET6) and address[0] not in LOCAL:
        raise OSError(f"public-clone test: network access to {address}")
    return _connect(self, address)
socket.socket.connect = connect
_getaddrinfo = socket.getaddrinfo
def getaddrinfo(host, *args, **kwargs):
    if host not in LOCAL and host is not None:
        raise OSError(f"public-clone test: name lookup of {host}")
    return _getaddrinfo(host, *args, **kwargs)
socket.getaddrinfo = getaddrinfo
sys.argv = ["matspray", *sys.argv[1:]]
runpy.run_module("matspray", run_name="__main__", alter_sys=True)
"""


def repository_files() -> list[str]:
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError) as error:
        pytest.skip(f"the repository's file list needs git and a git checkout ({error})")
    return [name for name in listed.decode().split("\0") if name and (ROOT / name).is_file()]


def needs(module: str) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        pytest.skip(f"the public-clone test runs the demo and the viewer: {module} is not installed (make test)")


class Clone:
    def __init__(self, base: Path):
        self.root = base / "matspray-clone"
        self.env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(base / "home")}
        (base / "home").mkdir()

    def command(self, *args) -> list[str]:
        return [sys.executable, "-c", GUARD, *map(str, args)]

    def run(self, *args, timeout: float = 300) -> subprocess.CompletedProcess:
        result = subprocess.run(
            self.command(*args), cwd=self.root, env=self.env, capture_output=True, text=True, timeout=timeout
        )
        assert result.returncode == 0, f"matspray {' '.join(map(str, args))}:\n{result.stdout[-3000:]}{result.stderr}"
        assert "Traceback" not in result.stderr and "public-clone test:" not in result.stderr, result.stderr
        return result


@pytest.fixture(scope="module")
def clone(tmp_path_factory) -> Clone:
    needs("mitsuba")
    needs("viser")
    base = tmp_path_factory.mktemp("public")
    clone = Clone(base)
    for name in repository_files():
        target = clone.root / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    for cached in sorted((ROOT / "matspray").glob("**/__pycache__/*.nb[ic]")):
        target = clone.root / cached.relative_to(ROOT)
        target.parent.mkdir(exist_ok=True)
        shutil.copy2(cached, target)
    assert not (base / "shared").exists() and sorted(p.name for p in base.iterdir()) == ["home", "matspray-clone"]
    return clone


@pytest.mark.slow
def test_a_public_clone_runs_the_first_commands_without_shared_data_or_network(clone):
    where = subprocess.run(
        [sys.executable, "-c", "import matspray; print(matspray.__file__)"],
        cwd=clone.root,
        env=clone.env,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert Path(where).resolve().is_relative_to(clone.root.resolve()), where  # the clone's code, not this tree's

    demo = clone.run("demo", "--preset", "test", "--out", "runs/demo", *FEWER_STEPS)
    tables = (clone.root / "runs" / "demo" / "run" / "eval" / "tables.md").read_text()
    assert "report:" in demo.stdout and "## Table 1" in tables
    # no LPIPS weights in a fresh HOME: one line saying how to get them, not an error
    assert "- LPIPS: n/a: torchvision's AlexNet weights are not at " in tables
    assert "python -m matspray.eval.lpips --download" in tables

    data = capture_like(clone.root / "runs" / "demo" / "data", clone.root / "capture")
    assert "format: blender" in clone.run("info", "--data", data).stdout
    clone.run("run", "--data", data, "--out", "runs/capture", "--preset", "test", *FEWER_STEPS)
    assert (clone.root / "runs" / "capture" / "asset-photos-only" / "asset.ply").is_file()

    report = clone.run("eval", "--run", "runs/capture")  # its default lights: studio sunset forest
    assert "a real capture" in report.stdout
    figures = {p.name for p in (clone.root / "runs" / "capture" / "report").iterdir()}
    for light in ("studio", "sunset", "forest"):
        assert any(f"_{light}" in name for name in figures), (light, sorted(figures))

    from matspray.render.shade.lights import list_envmaps

    names = list_envmaps()
    assert {"sky", "studio", "sunset", "overcast", "city", "forest", "interior", "sunrise"} <= set(names)
    clone.run("relight", "--run", "runs/capture", "--env", *names, "--out", "relit")
    written = sorted(p.name for p in (clone.root / "relit").iterdir())
    assert written == sorted(f"r_{i:03d}_{name}.png" for i in range(2) for name in names)

    assert "camera poses" in clone.run("colmap", "--help").stdout
    start_and_stop_the_viewer(clone)


def start_and_stop_the_viewer(clone: Clone) -> None:
    port = free_port()
    command = clone.command("view", "--run", "runs/capture", "--port", port)
    stopped = serve_then_interrupt(command, port, stop_timeout=60, cwd=clone.root, env=clone.env)
    assert stopped.page_status == 200 and b"<html" in stopped.page.lower()  # the page is served
    out, err = stopped.out, stopped.err
    assert stopped.returncode == 0, "".join(stopped.lines) + out + err
    assert "matspray view: stopped" in out and "Traceback" not in err, out + err
