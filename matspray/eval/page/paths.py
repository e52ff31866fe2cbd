"""What the report calls the object, and what keeps the machine's paths off the page.

A report is shared: copied, zipped, sent. The folders of the machine it was made on (the run's, the dataset's, the
home folder, torch's cache) mean nothing elsewhere and tell what they should not, so the page names the run folder
'.', the dataset by its folder's name, and any other absolute path by its last part ('…/name')."""

from __future__ import annotations

import re
from pathlib import Path

from matspray.data.formats.blender import read_scene_json
from matspray.eval.lpips import ALEXNET_MB, DOWNLOAD_HINT, WEIGHTS_ENV

GENERIC_FOLDERS = ("data", "dataset")  # a dataset folder named like this says nothing: its parent names the object
# an absolute path (or one in the home folder, '~/...') where a word starts: after a space, a bracket, a quote, or '>'
# or '=' of the markup; two parts at least, so that the markup's '</b>' and '/>', a '1/2' and a URL's '//' stay
ABSOLUTE_PATH = re.compile(r"(?<=[\s(\[{'\"`>=])(?:~|/[\w.+@%-]+)(?:/[\w.+@%-]+)+/?")
LAST_PART = re.compile(r"[^/]+(?=/?$)")


def object_name(data) -> str:
    """The object's name for a page's title: a `matspray synth` object's asset or shape and seed, else the dataset's
    folder (its parent's name where the folder is called 'data' or 'dataset', as the demo's is)."""
    data = Path(data)
    record = read_scene_json(data) or {}
    asset = record.get("asset")
    if isinstance(asset, dict) and isinstance(asset.get("file"), str):
        return Path(asset["file"]).stem
    if isinstance(record.get("shape"), str):
        seed = record.get("seed")
        return f"{record['shape']} (seed {seed})" if seed is not None else record["shape"]
    folder = data.resolve()
    if folder.name.lower() in GENERIC_FOLDERS and folder.parent.name:
        return folder.parent.name
    return folder.name


def page_places(run_root, data=None) -> dict[str, str]:
    """{absolute path: what the page writes instead}: the run folder as '.', the dataset by its folder's name, the
    home folder as '~'."""
    places = {str(Path.home()): "~"}
    if data is not None:
        places[str(Path(data).resolve())] = f"the dataset ({Path(data).resolve().name})"
        places[str(Path(data))] = places[str(Path(data).resolve())]
    places[str(Path(run_root).resolve())] = "."
    places[str(Path(run_root))] = "."
    return places


def without_machine_paths(text: str, places: dict[str, str]) -> str:
    """`text` with each of `places` (longest first) written as given, and any other absolute path as '…/' and its
    last part; a path starting with '~' (the home folder) is left as it is."""
    for place in sorted((p for p in places if p not in ("", "/", ".")), key=len, reverse=True):
        # the whole folder only: '/root' is not the start of '/rootfs'
        text = re.sub(re.escape(place) + r"(?![\w.-])", lambda _, place=place: places[place], text)

    def shorten(match: re.Match) -> str:
        path = match.group(0)
        if path.startswith("~"):
            return path
        last = LAST_PART.search(path)
        return f"…/{last.group(0)}" if last else "…"

    return ABSOLUTE_PATH.sub(shorten, text)


def lpips_line(source: str | None) -> str | None:
    """The LPIPS source of metrics.json as a page says it: where the weights are missing, how to get them (without
    the cache's path on this machine); else the source, its weights file named by its last part."""
    if not source:
        return source
    if source.startswith("n/a"):
        return (
            f"n/a: no LPIPS weights on the machine that made this report; get them once ({ALEXNET_MB} MB, into "
            f"torch's cache) with `{DOWNLOAD_HINT}`, or pass --lpips-weights FILE.npz (or set ${WEIGHTS_ENV})"
        )
    return without_machine_paths(f" {source}", {})[1:]
