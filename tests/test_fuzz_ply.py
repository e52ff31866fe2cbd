"""Property-based tests of Gaussian PLY reading: a small 3DGS PLY with materials (an asset's asset.ply) written by
`write_ply`, holding NaN or Inf values or the zero quaternion (refused, naming the row), with a header line edited (the
vertex count, a property's type or name, the format), then truncated at any byte or with random bytes flipped, read by
`read_ply` and `read_asset`.

Each reader refuses with a one-line MatsprayError naming the file, or returns finite Gaussians, normals and
materials; an intact file of finite values comes back as written, with the written count.
"""

from __future__ import annotations

import tempfile
from dataclasses import fields
from pathlib import Path

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from matspray.geometry.ply import read_ply, write_ply
from matspray.method.asset import CHANNELS, read_asset
from tests.fuzzing import damaged, read_or_refuse
from tests.test_fuzz_images import damage
from tests.test_fuzz_transforms import FUZZ
from tests.test_ply import random_gaussians

SPECIALS = st.sampled_from([float("nan"), float("inf"), -float("inf")])
COUNTS = st.sampled_from(["0", "1", "2", "5", "-1", "99999999999", "abc", "", "1.5"])
TYPES = st.sampled_from(["float", "double", "uchar", "int", "list uchar float", "float float", "bogus", ""])
NAMES = st.sampled_from(["x", "rot_0", "f_rest_0", "f_rest_99", "nx", "roughness", "", "x y"])
FORMATS = st.sampled_from(["ascii", "binary_big_endian", "binary_little_endian", "binary", "ascii 2.0", ""])


@st.composite
def header_edits(draw, lines: list[str]):
    """(index of a header line, its new text): the vertex count, a property's type or name, or the format."""
    kind = draw(st.sampled_from(["count", "type", "name", "format", "drop"]))
    if kind == "count":
        vertex = next(line for line in lines if line.startswith("element vertex"))
        return lines.index(vertex), f"element vertex {draw(COUNTS)}"
    if kind == "format":
        return 1, f"format {draw(FORMATS)} 1.0"
    index = draw(st.integers(0, len(lines) - 1).filter(lambda i: lines[i].startswith("property")))
    _, kind_, name = lines[index].split(" ")
    if kind == "type":
        return index, f"property {draw(TYPES)} {name}"
    return index, "" if kind == "drop" else f"property {kind_} {draw(NAMES)}"


def fields_of(gaussians) -> list[torch.Tensor]:
    return [getattr(gaussians, f.name) for f in fields(gaussians)]


@pytest.fixture(scope="module")
def folder():
    return Path(tempfile.mkdtemp(prefix="fuzz-ply-"))


@FUZZ
@given(count=st.integers(0, 4), sh_bases=st.sampled_from([1, 4]), seed=st.integers(0, 2**16), data=st.data())
def test_gaussian_ply(folder, count, sh_bases, seed, data):
    gaussians = random_gaussians(count, sh_bases, seed)
    normals, materials = torch.randn(count, 3), torch.rand(count, len(CHANNELS))
    tensors = [gaussians.means, gaussians.sh, gaussians.quats, normals, materials]
    finite = True
    for _ in range(data.draw(st.integers(0, 2)) if count else 0):  # a NaN or Inf in any field
        index = data.draw(st.integers(0, len(tensors) - 1), label="field")
        tensor = tensors[index]
        tensor.view(-1)[data.draw(st.integers(0, tensor.numel() - 1))] = data.draw(SPECIALS)
        finite = False
    zero_rows = data.draw(st.lists(st.integers(0, count - 1), max_size=2, unique=True)) if count else []
    for row in zero_rows:  # a Gaussian with no rotation: the zero quaternion (or one too small to normalise)
        gaussians.quats[row] = data.draw(st.sampled_from([0.0, -0.0, 1e-30, 1e-40]))
    path = folder / "asset.ply"
    write_ply(path, gaussians, normals, extra=dict(zip(CHANNELS, materials.T)))
    blob = path.read_bytes()
    head_end = blob.index(b"end_header\n") + len(b"end_header\n")
    edit = data.draw(st.one_of(st.none(), header_edits(blob[:head_end].decode().split("\n"))))
    if edit is not None:
        lines = blob[:head_end].decode().split("\n")  # the last one is the "" after end_header's newline
        if edit[1]:
            lines[edit[0]] = edit[1]
        else:  # the property's line dropped, the rest of the header as it was
            del lines[edit[0]]
        blob = "\n".join(lines).encode() + blob[head_end:]
    cut, flips = data.draw(st.one_of(st.just((None, [])), damage(len(blob))))
    path.write_bytes(damaged(blob, cut, flips))

    read = read_or_refuse(lambda: read_ply(path, extra=CHANNELS), path, "read_ply ")
    asset = read_or_refuse(lambda: read_asset(folder), path, "read_asset ")
    if read is not None:
        got, got_normals, got_extra = read
        for tensor in (*fields_of(got), *([got_normals] if got_normals is not None else []), *got_extra.values()):
            assert torch.isfinite(tensor).all()
        assert (got.quats.double().norm(dim=-1) >= 1e-12).all(), "a Gaussian without a rotation is accepted"
    if asset is not None:
        assert all(torch.isfinite(t).all() for t in (asset.materials, asset.normals, *fields_of(asset.gaussians)))
    if edit is None and cut is None and not flips and finite and not zero_rows:
        assert read is not None and asset is not None, "an intact file is refused"
        assert len(got) == count and torch.equal(got.means, gaussians.means) and torch.equal(got.sh, gaussians.sh)
        assert torch.equal(got_normals, normals) and torch.equal(torch.stack(list(got_extra.values()), -1), materials)
