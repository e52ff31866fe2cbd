"""Entries a camera file lists more than once (the same frame twice in a transforms file, two COLMAP images of one
name or id): refused in one line that names the file and the repeated entries, before any image is read. An image path
is compared as exporters vary it (backslashes, './', the suffix left out). Two entries
of one view would train it twice, or under two poses, and leave the other views' names ambiguous."""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from matspray.errors import file_error

SHOWN = 3  # repeated keys named in a message; more are counted


def normalised(name: str) -> str:
    return PurePosixPath(str(name).replace("\\", "/")).as_posix().removeprefix("./")


def without_suffix(name: str) -> str:
    """`name` normalised, without its suffix (split lists may omit it); names with no file name ('.')
    stay as they are."""
    path = PurePosixPath(normalised(name))
    return str(path.with_suffix("")) if path.name not in ("", ".", "..") else str(path)


def refuse_repeats(path: Path, keys: list, what: str, entry: str, hint: str, labels: list | None = None) -> None:
    """Raise a one-line DataError naming `path` when a key occurs twice in `keys` (one per entry of the file, in its
    order): each repeated key with the positions of its entries (`what`: what a key is, 'view'; `entry`: what the
    file calls its entries, 'frames'; `hint`: what to do; `labels`: how the file numbers its entries, default their
    positions)."""
    where: dict = {}
    for index, key in enumerate(keys):
        where.setdefault(key, []).append(index if labels is None else labels[index])
    repeats = [(key, places) for key, places in where.items() if len(places) > 1]
    if not repeats:
        return
    shown = ", ".join(
        f"{what} '{key}' {len(places)} times ({entry} {', '.join(map(str, places))})" for key, places in repeats[:SHOWN]
    )
    more = f", and {len(repeats) - SHOWN} more {what}s more than once" if len(repeats) > SHOWN else ""
    raise file_error(path, f"lists {shown}{more}", hint)
