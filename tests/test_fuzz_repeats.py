"""Property-based tests of entries a camera file lists more than once, in every format the readers take: frames of a
Blender transforms_train.json or a nerfstudio transforms.json (the same image under another spelling, with the same
or another pose), names repeated in nerfstudio's split lists, and COLMAP cameras or images repeated (same id, or one
image name under two ids) in a text or a binary model.

A file with a repeated entry is refused in one line naming the file and the repeated view (or id); a file without
one loads as a usable scene (tests/test_fuzz_transforms.py: check_scene)."""

from __future__ import annotations

import json
import re
import struct
import tempfile
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from matspray.data.loader import load_scene
from tests.fuzzing import colmap_model, read_or_refuse
from tests.test_fuzz_transforms import FUZZ, check_scene
from tests.test_readers import C2W_GL, FOV_X, write_rgba

FEW = settings(FUZZ, max_examples=40)  # each example reads a dataset
VIEWS = 4
SPELLINGS = ("{}", "{}.png", "./{}")  # one image, as exporters write its path
MOVED = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]  # another pose of the same photo


def load_or_refuse(root: Path, named: Path, repeated: list[str]):
    """A repeated entry: refused in one line naming `named` and the first repeated keys. Else a usable scene."""
    scene = read_or_refuse(lambda: load_scene(root, test_every=0), root)
    if repeated:
        assert scene is None, f"{named.name} repeats {repeated} and was read"
        return
    assert scene is not None, f"{named.name} has no repeated entry and was refused"
    check_scene(scene)


def refusal(root: Path) -> str:
    try:
        load_scene(root, test_every=0)
    except Exception as exc:  # noqa: BLE001 - the property below checks what it is
        return str(exc)
    return ""


def repeats(keys: list) -> list:  # the keys listed more than once, in the order they first appear
    return [key for key in dict.fromkeys(keys) if keys.count(key) > 1]


frame_lists = st.lists(
    st.tuples(st.integers(0, VIEWS - 1), st.sampled_from(SPELLINGS), st.booleans()), min_size=1, max_size=6
)  # (view, how its path is spelt, whether its pose is another)


@pytest.fixture(scope="module")
def images():
    root = Path(tempfile.mkdtemp(prefix="fuzz-repeats-"))
    for i in range(VIEWS):
        write_rgba(root / "train" / f"r_{i:03d}.png")
    return root


def frames_of(entries, folder: str) -> list[dict]:
    return [
        {"file_path": spelling.format(f"{folder}/r_{i:03d}"), "transform_matrix": MOVED if moved else C2W_GL}
        for i, spelling, moved in entries
    ]


@FEW
@given(entries=frame_lists)
def test_blender_frames_listed_twice(images, entries):
    path = images / "transforms_train.json"
    path.write_text(json.dumps({"camera_angle_x": FOV_X, "frames": frames_of(entries, "train")}))
    repeated = [f"train/r_{i:03d}" for i in repeats([i for i, _, _ in entries])]
    load_or_refuse(images, path, repeated)
    if repeated:
        message = refusal(images)
        assert message.startswith(f"{path}: lists image '{repeated[0]}' ") and "times (frames " in message, message
        for name in repeated[:3]:
            assert f"'{name}'" in message


@FEW
@given(entries=frame_lists, split=st.lists(st.integers(0, VIEWS - 1), min_size=1, max_size=5), use_split=st.booleans())
def test_nerfstudio_frames_and_split_lists_listed_twice(tmp_path_factory, entries, split, use_split):
    root = tmp_path_factory.mktemp("nerfstudio")
    for i in range(VIEWS):
        write_rgba(root / "images" / f"r_{i:03d}.png")
    listed = sorted({i for i, _, _ in entries})
    names = [listed[k % len(listed)] for k in split]  # the split list names frames that exist
    meta = {"camera_angle_x": FOV_X, "frames": frames_of(entries, "images")}
    if use_split:
        meta["train_filenames"] = [f"images/r_{i:03d}.png" for i in names]
    path = root / "transforms.json"
    path.write_text(json.dumps(meta))
    repeated = [f"images/r_{i:03d}" for i in repeats([i for i, _, _ in entries])]
    in_split = [f"images/r_{i:03d}" for i in repeats(names)] if use_split and not repeated else []
    load_or_refuse(root, path, repeated + in_split)
    if repeated or in_split:
        message = refusal(root)
        assert message.startswith(f"{path}: lists "), message
        assert f"'{(repeated or in_split)[0]}'" in message, message


pycolmap_tests = pytest.mark.skipif(
    __import__("importlib").util.find_spec("pycolmap") is None, reason="pycolmap (the colmap extra) is not installed"
)


@pytest.fixture(scope="module")
def colmap_text():
    """(dataset folder, its text model, its binary model): three images, one camera."""
    return colmap_model("fuzz-repeats-colmap-")


def data_lines(text: str) -> list[str]:
    return [line for line in text.split("\n") if not line.startswith("#")]


@pycolmap_tests
@FEW
@given(
    which=st.sampled_from(["camera", "image id", "image name"]),
    entry=st.integers(0, 2),
    changed=st.booleans(),
)
def test_colmap_text_entries_listed_twice(colmap_text, which, entry, changed):
    root, intact, _ = colmap_text
    folder = root / "sparse" / "0"
    for name, text in intact.items():
        (folder / name).write_text(text)
    if which == "camera":
        path, lines = folder / "cameras.txt", data_lines(intact["cameras.txt"])
        line = lines[0].split()
        if changed:  # the same id with another focal length
            line[4] = "60.0"
        (folder / "cameras.txt").write_text(intact["cameras.txt"] + " ".join(line) + "\n")
        key = line[0]
    else:
        path, lines = folder / "images.txt", [line for line in data_lines(intact["images.txt"])]
        pose = lines[2 * entry].split()
        if which == "image name":
            pose[0] = "99"  # another id, the same photo
        if changed:
            pose[5] = str(float(pose[5]) + 0.25)  # another pose
        (folder / "images.txt").write_text(intact["images.txt"] + " ".join(pose) + "\n\n")
        key = pose[-1].rsplit(".", 1)[0] if which == "image name" else pose[0]
    load_or_refuse(root, path, [key])
    message = refusal(root)
    assert message.startswith(f"{path}: lists ") and f"'{key}'" in message, message


def record_end(blob: bytes, start: int, kind: str) -> int:
    """The end of the record at `start` of a COLMAP cameras.bin or images.bin."""
    if kind == "cameras":
        model = struct.unpack_from("<i", blob, start + 4)[0]
        return start + 24 + 8 * {0: 3, 1: 4, 2: 4, 3: 5, 4: 8}[model]
    name_end = blob.index(b"\0", start + 64)
    (points,) = struct.unpack_from("<Q", blob, name_end + 1)
    return name_end + 9 + 24 * points


@pycolmap_tests
@FEW
@given(kind=st.sampled_from(["cameras", "images"]), new_id=st.booleans())
def test_colmap_binary_entries_listed_twice(colmap_text, kind, new_id):
    root, intact, binaries = colmap_text
    folder = root / "sparse" / "0"
    for name in intact:
        (folder / name).unlink(missing_ok=True)
    for name, blob in binaries.items():
        (folder / name).write_bytes(blob)
    blob = binaries[f"{kind}.bin"]
    (count,) = struct.unpack_from("<Q", blob, 0)
    record = bytearray(blob[8 : record_end(blob, 8, kind)])
    repeated_id = kind == "cameras" or not new_id
    if not repeated_id:  # images.bin: the same photo under another id
        record[0:4] = struct.pack("<i", 99)
    path = folder / f"{kind}.bin"
    path.write_bytes(struct.pack("<Q", count + 1) + blob[8:] + bytes(record))
    key = str(struct.unpack_from("<i", record, 0)[0]) if repeated_id else re.sub(r"\..*", "", "img0.png")
    load_or_refuse(root, path, [key])
    message = refusal(root)
    assert message.startswith(f"{folder}") and f"'{key}'" in message, message


def test_a_frame_listed_twice_names_the_file_and_the_frame(images):
    """the message listed no repeated name and named neither the file nor the view."""
    from matspray.errors import DataError

    path = images / "transforms_train.json"
    path.write_text(
        json.dumps(
            {
                "camera_angle_x": FOV_X,
                "frames": frames_of([(0, "{}", False), (1, "{}", False), (0, "{}.png", True)], "train"),
            }
        )
    )
    with pytest.raises(DataError) as caught:
        load_scene(images)
    assert str(caught.value) == (
        f"{path}: lists image 'train/r_000' 2 times (frames 0, 2) (list each view once: remove the repeated frames)"
    )
