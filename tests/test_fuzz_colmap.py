"""Property-based tests of the COLMAP reader: a small text model (cameras.txt, images.txt) with one number or
word replaced by a bad one (NaN, Inf, zero, negative, too large, not a number, empty), or a file truncated.

Either load_scene refuses with a one-line MatsprayError naming a file of the dataset, or it returns a usable
scene (tests/test_fuzz_transforms.py: check_scene). A non-unit quaternion is normalised, as COLMAP does.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.fuzzing import colmap_model
from tests.test_fuzz_transforms import FUZZ, load_or_refuse

pycolmap = pytest.importorskip("pycolmap")

FILES = ("cameras.txt", "images.txt")
TOKENS = st.sampled_from(
    ["nan", "inf", "-inf", "0", "-0", "-1", "-45", "1e400", "1e-320", "1e30", "abc", "", "3.5", "PINHOLE", "9"]
)


@pytest.fixture(scope="module")
def model():
    """(dataset folder, its text files' intact contents): the text model is what is fuzzed."""
    root, texts, _ = colmap_model("fuzz-colmap-")
    return root, texts


def replace_token(text: str, line: int, column: int, token: str) -> str:
    """`text` with one token of its `line`-th data line (comments skipped) replaced by `token`."""
    lines = text.split("\n")
    data = [i for i, content in enumerate(lines) if content.strip() and not content.startswith("#")]
    if not data:
        return text
    target = data[line % len(data)]
    words = lines[target].split(" ")
    words[column % len(words)] = token
    lines[target] = " ".join(words)
    return "\n".join(lines)


@FUZZ
@given(
    name=st.sampled_from(FILES),
    line=st.integers(0, 5),
    column=st.integers(0, 11),
    token=TOKENS,
    cut=st.one_of(st.none(), st.integers(0, 400)),
)
def test_corrupted_colmap_text_model(model, name, line, column, token, cut):
    root, intact = model
    folder = root / "sparse" / "0"
    for file_name, text in intact.items():
        (folder / file_name).write_text(text)
    text = replace_token(intact[name], line, column, token)
    (folder / name).write_text(text if cut is None else text[:cut])
    load_or_refuse(root)
