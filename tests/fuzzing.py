"""Helpers shared by the property-based tests of file readers (tests/test_fuzz_*.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, TypeVar

from hypothesis import event

from matspray.errors import MatsprayError

T = TypeVar("T")


def damaged(blob: bytes, cut: int | None, flips) -> bytes:
    """`blob` with bytes at offsets set to values (`flips`, as tests.test_fuzz_images.damage draws them), then cut
    to its first `cut` bytes (None: all)."""
    out = bytearray(blob)
    for offset, value in flips:
        out[offset] = value
    return bytes(out[:cut] if cut is not None else out)


def read_or_refuse(read: Callable[[], T], path: Path, label: str = "") -> T | None:
    """The property of every reader: a one-line MatsprayError naming `path`, or a result (checked by the caller)."""
    try:
        result = read()
    except MatsprayError as exc:
        message = str(exc)
        assert "\n" not in message, message
        assert str(path) in message, message
        event(f"{label}refused: {type(exc).__name__}")
        return None
    event(f"{label}accepted")
    return result


def colmap_model(prefix: str) -> tuple[Path, dict[str, str], dict[str, bytes]]:
    """A COLMAP dataset of three images and one camera (tests.test_readers.write_colmap) in a new folder, its model
    as text: (folder, the text files' contents, the binary files' contents, removed from the folder)."""
    import tempfile

    import pycolmap

    from tests.test_readers import write_colmap

    root = Path(tempfile.mkdtemp(prefix=prefix))
    write_colmap(root, n_images=3)
    folder = root / "sparse" / "0"
    pycolmap.Reconstruction(str(folder)).write_text(str(folder))
    binaries = {path.name: path.read_bytes() for path in folder.glob("*.bin")}
    for binary in folder.glob("*.bin"):
        binary.unlink()
    return root, {path.name: path.read_text() for path in folder.glob("*.txt")}, binaries
