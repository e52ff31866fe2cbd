"""The first half second of `matspray view`: the checks that need no torch (the run folder and its asset, the lights
given, the port) and the page, opened before torch, the asset and the light load, so that the browser loads viser's
page while they do (the viewer attaches to it when ready; clients that came first are served then).

Nothing here imports torch: `matspray.cli.view` calls it first."""

from __future__ import annotations

import contextlib
import io
import socket
from dataclasses import dataclass
from pathlib import Path

from matspray.errors import ConfigError, RunError
from matspray.files import HDR_SUFFIXES
from matspray.rundir import RunDir

LOADING = "**matspray view** loading the run…"


def run_variants(root) -> list[str]:
    """The variants with an asset in run folder `root`, the one the viewer starts with first (`RunDir.default_variant`:
    full, else photos-only); RunError (one line naming the command to run first) when it is no run folder or holds no
    asset."""
    root = Path(root)
    if not root.is_dir():
        raise RunError(f"{root}: no such run folder; make one with `matspray run --data DATA --out {root}`")
    run = RunDir(root).require()
    first = run.default_variant()  # RunError in one line when there is none
    return [first] + [v for v in run.asset_variants() if v != first]


def check_source(path) -> None:
    """What `view --run` names, checked as far as it can be without torch: a run folder with an asset
    (`run_variants`), or an existing .glb (its splats and materials are checked when it is read)."""
    path = Path(path)
    if path.suffix.lower() != ".glb":
        run_variants(path)
    elif not path.is_file():
        raise RunError(f"{path}: no such file; write it with `matspray export --run RUN --splats {path}`")


def light_files(paths) -> list[Path]:
    """The .exr/.hdr files that `--env` names: files as given (any suffix: a wrong one is reported when the light is
    chosen), folders by their .exr/.hdr files. A path that does not exist is a ConfigError of one line."""
    files: list[Path] = []
    for path in map(Path, paths):
        path = path.expanduser()
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in HDR_SUFFIXES)
            if not found:
                raise ConfigError(f"--env {path}: the folder holds no .exr or .hdr file")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise ConfigError(f"--env {path}: no such file or folder")
    unique: list[Path] = []
    for path in files:
        if path.resolve() not in [p.resolve() for p in unique]:
            unique.append(path)
    return unique


def port_problem(host: str, port: int) -> str | None:
    """None when `port` can be listened on at `host`, else one line with the port and what to pass instead."""

    def free(number: int) -> bool:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.setsockopt(
                socket.SOL_SOCKET, socket.SO_REUSEADDR, 1
            )  # as the server binds: a port in TIME_WAIT is free
            try:
                probe.bind((host, number))
            except OSError:
                return False
        return True

    if not 0 < port < 65536:
        return f"--port {port}: a port is a number from 1 to 65535"
    if free(port):
        return None
    other = next((p for p in range(port + 1, min(port + 50, 65536)) if free(p)), None)
    instead = f"pass --port {other} (free now)" if other else "pass another --port"
    return f"port {port} on {host} is in use (another viewer or program listens there); {instead}, or stop what uses it"


@dataclass
class Page:
    """A viser server already serving the page, with a note saying the run is loading (removed once it is)."""

    server: object  # viser.ViserServer
    loading: object  # its GUI markdown handle

    @property
    def url(self) -> str:
        host = self.server.get_host()
        shown = "localhost" if host in ("127.0.0.1", "0.0.0.0", "::", "::1", "localhost") else host
        return f"http://{shown}:{self.server.get_port()}"

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            self.server.stop()


def open_page(host: str, port: int) -> Page:
    """Start viser's server on `host`:`port` (ConfigError of one line when the port cannot be used)."""
    try:
        import viser
    except ImportError:
        raise ConfigError("the viewer needs viser: pip install 'matspray[view]'") from None
    problem = port_problem(host, port)
    if problem:
        raise ConfigError(problem)
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner of its own; the CLI prints the URL
        server = viser.ViserServer(host=host, port=port, label="MatSpray", verbose=False)
    return Page(server, server.gui.add_markdown(LOADING))
