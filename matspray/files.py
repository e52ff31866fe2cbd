"""File helpers that need no torch, so that a run folder can be checked before torch is imported (`matspray view`
opens its page first; see view/launch.py)."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from matspray.errors import ConfigError

HDR_SUFFIXES = (".exr", ".hdr")  # the high-dynamic-range image files MatSpray reads as lights


def atomic_target(path: Path) -> Path:
    """A temporary sibling of `path` to write into before `os.replace` (same folder, same suffix)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def leftover_temporaries(folder: Path) -> list[Path]:
    """The files in `folder` that `atomic_target` named for a process that is gone: a run killed in the middle of a
    write leaves its temporary behind, and nothing else would ever remove it."""
    leftovers = []
    for path in Path(folder).glob(".*.tmp-*"):
        pid = path.name.rsplit(".tmp-", 1)[1].split(".", 1)[0]
        if pid.isdigit() and path.is_file() and not _process_running(int(pid)):
            leftovers.append(path)
    return leftovers


def _process_running(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` atomically (a reader never sees half a file), making the folder when needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    tmp.write_text(text)
    os.replace(tmp, path)


def check_output_folder(folder: Path, named) -> Path:
    """`folder` can be made (or is a folder) and written into, checked before any work and without making anything;
    a ConfigError that names `named` (the output asked for: the folder, or a file to be written in it) when not."""
    folder = Path(folder)
    existing = next(p for p in (folder, *folder.parents) if p.exists())  # the root at the latest
    if not existing.is_dir():
        which = "" if existing == Path(named) else f"{existing} "
        raise ConfigError(f"{named}: {which}is a file, not a folder; choose another output path")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{named}: {existing} cannot be written (permission denied); choose another output path")
    return folder


def check_output_file(out: Path, endings: str) -> Path:
    """A file `out` can be written (not a folder, in a folder that is or can be made), checked before any work;
    `endings`: the file names it may have, for the message (".glb")."""
    out = Path(out)
    if out.is_dir():
        raise ConfigError(f"{out}: is a folder; give a file name ending in {endings}")
    check_output_folder(out.parent, out)
    if out.exists() and not os.access(out, os.W_OK):
        raise ConfigError(f"{out}: cannot be written (permission denied); choose another output path")
    return out


def to_plain(value):
    """Dataclasses, paths and tuples as plain JSON/YAML values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def write_json(path: Path, data) -> None:
    """`data` (dataclasses and paths included, see `to_plain`) as indented JSON, written atomically."""
    write_text_atomic(path, json.dumps(to_plain(data), indent=2, sort_keys=False) + "\n")


def read_json(path: Path):
    return json.loads(Path(path).read_text())
