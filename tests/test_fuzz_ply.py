"""Property-based tests of Gaussian PLY reading: a small 3DGS PLY with materials (an asset's asset.ply) written by
`write_ply`, holding NaN or Inf values or the zero quaternion (refused, naming the row), with a header line edited (the
vertex count, a property's type or name, the format) or a property's line dropped, then truncated at any byte or
with random bytes flipped, read by `read_ply` and `read_asset`.

Each reader refuses with a one-line MatsprayError naming the file, or returns finite Gaussians, normals and
materials; an intact file of finite values comes back as written, with the written count; a file lacking one
property is refused with the message that names it (an asset without normals: the one that says so).
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import fields
from pathlib import Path

import pytest
import torch
from hypothesis import event, given
from hypothesis import strategies as st

from matspray.errors import MatsprayError
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
# the 3DGS layout's own properties, written out here rather than taken from the reader
GAUSSIAN_PROPERTIES = {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"} | {f"scale_{i}" for i in range(3)}
GAUSSIAN_PROPERTIES |= {f"rot_{i}" for i in range(4)}


@st.composite
def header_edits(draw, lines: list[str]):
    """(index of a header line, its new text): the vertex count, a property's type or name, or the format."""
    kind = draw(st.sampled_from(["count", "type", "name", "format", "drop"]))
    if kind == "count":
        vertex = next(line for line in lines if line.startswith("element vertex"))
        return lines.index(vertex), f"element vertex {draw(COUNTS)}"
    if kind == "format":
        return 1, f"format {draw(FORMATS)} 1.0"
    index = draw(st.sampled_from([i for i, line in enumerate(lines) if line.startswith("property")]))
    _, kind_, name = lines[index].split(" ")
    if kind == "type":
        return index, f"property {draw(TYPES)} {name}"
    return index, "" if kind == "drop" else f"property {kind_} {draw(NAMES)}"


def dropped_property_refusals(name: str, sh_bases: int) -> tuple[str | None, str]:
    """What read_ply and read_asset say of a well-formed PLY whose header lacks property `name` (read_ply's None:
    it reads the file), its other values finite. Dropping a float32 column shifts the binary rows by 4 bytes, so
    every value read is still one of the finite float32 values written."""
    if name in GAUSSIAN_PROPERTIES:
        said = f"lacks the 3DGS properties {name} "
        return said, said
    if name.startswith("f_rest_"):  # one of 3 (K - 1) coefficients gone: a count no SH degree has
        said = f"has {3 * (sh_bases - 1) - 1} f_rest properties, which is no SH degree"
        return said, said
    if name in ("nx", "ny", "nz"):  # the Gaussians read, but an asset needs its normals
        return None, "has no normals (nx, ny, nz)"
    assert name in CHANNELS, name
    said = f"lacks the properties {name} "
    return said, said


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
    dropped = None
    if edit is not None:
        lines = blob[:head_end].decode().split("\n")  # the last one is the "" after end_header's newline
        if edit[1]:
            lines[edit[0]] = edit[1]
        else:  # the property's line dropped, the rest of the header as it was
            dropped = lines[edit[0]].split(" ")[-1]
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
    if dropped is not None and cut is None and not flips:
        said_by_ply, said_by_asset = dropped_property_refusals(dropped, sh_bases)
        # the header's own checks come before the values'; a normal or material missing is seen after them
        if dropped in GAUSSIAN_PROPERTIES or dropped.startswith("f_rest_") or (finite and not zero_rows):
            event("a dropped property named by the readers")  # hypothesis --hypothesis-show-statistics counts them
            if said_by_ply is None:
                assert read is not None and read[1] is None, "a PLY without normals read with normals"
            else:
                with pytest.raises(MatsprayError, match=re.escape(f"{path}: {said_by_ply}")):
                    read_ply(path, extra=CHANNELS)
            with pytest.raises(MatsprayError, match=re.escape(f"{path}: {said_by_asset}")):
                read_asset(folder)
    if edit is None and cut is None and not flips and finite and not zero_rows:
        assert read is not None and asset is not None, "an intact file is refused"
        assert len(got) == count and torch.equal(got.means, gaussians.means) and torch.equal(got.sh, gaussians.sh)
        assert torch.equal(got_normals, normals) and torch.equal(torch.stack(list(got_extra.values()), -1), materials)


@pytest.mark.parametrize("sh_bases", [1, 4])
def test_each_dropped_property_is_named(tmp_path, sh_bases):
    """Every property's line dropped in turn from an asset.ply of 3 finite Gaussians, the header otherwise as
    written: the readers refuse with the message naming that property (the fuzz test above meets few of these)."""
    gaussians = random_gaussians(3, sh_bases, seed=5)
    path = tmp_path / "asset.ply"
    write_ply(path, gaussians, torch.randn(3, 3), extra=dict(zip(CHANNELS, torch.rand(3, len(CHANNELS)).T)))
    blob = path.read_bytes()
    head_end = blob.index(b"end_header\n") + len(b"end_header\n")
    lines = blob[:head_end].decode().split("\n")
    properties = [i for i, line in enumerate(lines) if line.startswith("property float ")]
    assert len(properties) == 3 + 3 + 3 * sh_bases + 1 + 3 + 4 + len(CHANNELS)  # the layout, then the materials
    for index in properties:
        name = lines[index].split(" ")[-1]
        path.write_bytes("\n".join(lines[:index] + lines[index + 1 :]).encode() + blob[head_end:])
        said_by_ply, said_by_asset = dropped_property_refusals(name, sh_bases)
        if said_by_ply is None:
            assert read_ply(path, extra=CHANNELS)[1] is None, name
        else:
            with pytest.raises(MatsprayError, match=re.escape(f"{path}: {said_by_ply}")):
                read_ply(path, extra=CHANNELS)
        with pytest.raises(MatsprayError, match=re.escape(f"{path}: {said_by_asset}")):
            read_asset(tmp_path)
