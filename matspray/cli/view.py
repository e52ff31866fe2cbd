"""`matspray view --run RUN`: a browser viewer that relights the run's asset live (viser; `matspray.view`)."""

import argparse
from pathlib import Path

from matspray.cli.options import add_compute_arguments
from matspray.presets import light_names


def add_view_parser(parser) -> None:
    parser.add_argument(
        "--run", type=Path, help="run folder made by `matspray run`, or a .glb made by `matspray export --splats`"
    )
    parser.add_argument("run_positional", nargs="?", type=Path, help=argparse.SUPPRESS)  # the old `view RUN`
    parser.add_argument(
        "--env",
        nargs="+",
        action="extend",
        default=[],
        metavar="FILE|FOLDER",
        help=f"HDR lights to offer besides the run's estimated light and the named lights ({light_names()}): "
        ".exr/.hdr files, or folders of them",
    )
    parser.add_argument("--port", type=int, default=8080, help="port to serve the page on (default 8080)")
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only; from another machine use "
        "ssh -L 8080:localhost:8080 HOST, or 0.0.0.0 to listen on every network)",
    )
    parser.add_argument(
        "--resolution",
        type=int,
        default=256,
        help="long side of the still picture in pixels (default 256; "
        "half while the camera moves); the page has a slider too",
    )
    add_compute_arguments(parser)


def view_main(args) -> int:
    import time

    from matspray.errors import ConfigError
    from matspray.view.launch import check_source, light_files, open_page

    args.run = args.run or args.run_positional
    if args.run is None:
        raise ConfigError("give the run folder: --run RUN")
    if not 32 <= args.resolution <= 4096:
        raise ConfigError(f"--resolution {args.resolution}: choose 32 to 4096 pixels")
    check_source(args.run)  # bad input is one line before anything starts
    light_files(args.env)
    page = open_page(args.host, args.port)  # served before torch loads: the browser opens the page meanwhile
    print(f"matspray view: {page.url}  ({args.run}; Ctrl+C stops)", flush=True)
    if args.host in ("127.0.0.1", "localhost", "::1"):
        print(
            f"  from another machine: ssh -L {args.port}:localhost:{args.port} THIS_HOST, then open {page.url} there",
            flush=True,
        )
    try:
        from matspray.render.backend import compute_target
        from matspray.view.server import Viewer, ViewerConfig

        device, backend = compute_target(args.device, args.backend)
        config = ViewerConfig(host=args.host, port=args.port, env=tuple(args.env), resolution=args.resolution)
        viewer = Viewer(args.run, config, device=device, backend=backend, page=page)
        viewer.start()
    except BaseException:
        page.stop()
        raise
    print(f"matspray view: ready ({backend} on {device})", flush=True)
    try:
        # short sleeps, not one long one: Ctrl+C's signal may land in another of the process's threads (torch's,
        # numba's, viser's); Python then only marks it for the main thread, which acts on it when it next wakes.
        # A main thread asleep for an hour did not stop (tests/test_view_stop.py: faulthandler showed it in sleep)
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        print("matspray view: stopped", flush=True)
    finally:
        viewer.stop()
    return 0
