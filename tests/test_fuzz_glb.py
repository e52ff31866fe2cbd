"""Property-based tests of glTF reading (`matspray synth --asset FILE` and `matspray eval --glb FILE`): a small textured
.glb written by `write_glb`, then damaged at the byte level (truncated at any byte, bytes flipped anywhere, in the JSON
chunk or in the binary chunk, the magic, version and length fields overwritten) or edited as a document that still
parses (any field set to a value of the wrong type or out of range, or dropped; a field added; positions, normals,
uvs or indices overwritten with NaN, Inf or out-of-range values; an image replaced by garbage, a truncated PNG or
another format), and as a .gltf beside its .bin (missing, truncated, padded).

Each file is read by `read_gltf` and turned into parts by `asset_parts` (what synth renders and `eval --glb` scores,
placed 'fit' and 'keep') and by `read_glb_parts`: either a one-line MatsprayError naming the file, or finite meshes
whose indices lie inside their vertices and textures in [0, 1]. An intact file comes back as written.
"""

from __future__ import annotations

import io
import json
import math
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("pygltflib")

from matspray.eval.glb import read_glb_parts  # noqa: E402
from matspray.gltf import PbrMaterial, Primitive, TextureRef, read_gltf, write_glb  # noqa: E402
from matspray.gltf.write import png_bytes  # noqa: E402
from matspray.synth.gltf_object import asset_parts  # noqa: E402
from tests.fuzzing import damaged, read_or_refuse  # noqa: E402
from tests.test_fuzz_images import damage  # noqa: E402
from tests.test_fuzz_transforms import FUZZ  # noqa: E402

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
QUAD_UVS = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
TETRA = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64) + 2.0
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
RNG = np.random.default_rng(7)
COLOUR = np.round(RNG.uniform(size=(4, 6, 3)) * 255) / 255
PACKED = np.round(RNG.uniform(size=(3, 5, 3)) * 255) / 255
PRIMITIVES = [
    Primitive("quad", QUAD, QUAD_FACES, (QUAD_UVS,), np.tile([0.0, 0.0, 1.0], (4, 1)), 0),
    Primitive("tetra", TETRA, TETRA_FACES, (), None, 1),
]
MATERIALS = [
    PbrMaterial(
        "textured",
        (1.0, 0.5, 0.25, 1.0),
        0.3,
        0.7,
        TextureRef(COLOUR, 0, wrap_s="clamp", wrap_t="mirror"),
        TextureRef(PACKED),
    ),
    PbrMaterial("plain", (0.2, 0.3, 0.4, 1.0), 1.0, 0.25),
]
EXTRAS = {"matspray": {"frame": "gltf", "variant": "full"}}

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = b"glTF", b"JSON", b"BIN\0"
# values a careless exporter or a damaged file puts into a field: wrong types, out-of-range indices and counts, NaN
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-3, 12),
    st.sampled_from(
        [
            255,
            4096,
            10**6,
            2**31,
            2**32 + 1,
            2**53,
            -(2**31),
            10**30,
            5120,
            5121,
            5122,
            5123,
            5124,
            5125,
            5126,
            5130,
            10497,
            33071,
            33648,
            0.5,
            -0.0,
            1.5,
            1e300,
            float("nan"),
            float("inf"),
            -float("inf"),
        ]
    ),
    st.sampled_from(
        [
            "",
            "VEC2",
            "VEC3",
            "VEC4",
            "SCALAR",
            "MAT2",
            "MAT4",
            "abc",
            "2.0",
            "OPAQUE",
            "BLEND",
            "missing.bin",
            "missing.png",
            "data:,",
            "data:application/octet-stream;base64,AAAA",
            "data:image/png;base64,!!",
            "KHR_texture_transform",
            "KHR_draco_mesh_compression",
        ]
    ),
)
VALUES = st.one_of(
    SCALARS,
    st.lists(SCALARS, max_size=17),
    st.dictionaries(st.sampled_from(["index", "texCoord", "count", "x"]), SCALARS, max_size=2),
)
ADDED_KEYS = [
    "byteStride",
    "normalized",
    "sparse",
    "matrix",
    "rotation",
    "scale",
    "translation",
    "children",
    "mode",
    "targets",
    "texCoord",
    "extensions",
    "sampler",
    "uri",
    "bufferView",
    "mimeType",
    "byteOffset",
    "scene",
    "skin",
    "extensionsRequired",
    "indices",
    "TEXCOORD_1",
    "NORMAL",
    "material",
    "baseColorFactor",
    "emissiveFactor",
    "frame",
    "run",
    "variant",
]
TRANSFORM = st.fixed_dictionaries(
    {
        "offset": st.lists(SCALARS, min_size=2, max_size=2),
        "rotation": SCALARS,
        "scale": st.lists(SCALARS, min_size=2, max_size=2),
    }
)
SPARSE = st.fixed_dictionaries(
    {
        "count": st.integers(-1, 6),
        "indices": st.fixed_dictionaries({"bufferView": st.integers(-1, 8), "componentType": SCALARS}),
        "values": st.fixed_dictionaries({"bufferView": st.integers(-1, 8)}),
    }
)
SPECIALS = [float("nan"), float("inf"), -float("inf"), 1e38, -1e38, 0.0]


def split(blob: bytes) -> tuple[dict, bytes]:
    """The JSON document and binary chunk of a .glb made by write_glb."""
    json_length = struct.unpack_from("<I", blob, 12)[0]
    document = json.loads(blob[20 : 20 + json_length])
    bin_length = struct.unpack_from("<I", blob, 20 + json_length)[0]
    return document, blob[28 + json_length : 28 + json_length + bin_length]


def pack(document: dict, binary: bytes) -> bytes:
    """A .glb of `document` and `binary`, every length field right (NaN written as JSON's NaN, which parsers meet)."""
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    binary = binary + b"\0" * (-len(binary) % 4)
    body = struct.pack("<I", len(text)) + JSON_CHUNK + text + struct.pack("<I", len(binary)) + BIN_CHUNK + binary
    return GLB_MAGIC + struct.pack("<II", 2, 12 + len(body)) + body


def paths(node, prefix=()):
    """Every key and index path below `node`."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield prefix + (key,)
            yield from paths(value, prefix + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield prefix + (index,)
            yield from paths(value, prefix + (index,))


def containers(node, prefix=()):
    """Paths of every object (dict) in the document, the root included."""
    if isinstance(node, dict):
        yield prefix
        for key, value in node.items():
            yield from containers(value, prefix + (key,))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from containers(value, prefix + (index,))


def at(document, path):
    for key in path:
        document = document[key]
    return document


@st.composite
def document_edits(draw, document: dict):
    """A function that edits a copy of `document`: one to three fields set, dropped or added."""
    leaves, objects = list(paths(document)), list(containers(document))
    edits = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["set", "set", "drop", "add", "transform", "sparse", "extras"]))
        if kind in ("set", "drop"):
            edits.append((kind, draw(st.sampled_from(leaves)), draw(VALUES) if kind == "set" else None))
        elif kind == "add":
            edits.append(("set", draw(st.sampled_from(objects)) + (draw(st.sampled_from(ADDED_KEYS)),), draw(VALUES)))
        elif kind == "transform":  # KHR_texture_transform on a texture of the first material
            which = draw(st.sampled_from(["baseColorTexture", "metallicRoughnessTexture"]))
            edits.append(
                (
                    "set",
                    ("materials", 0, "pbrMetallicRoughness", which, "extensions"),
                    {"KHR_texture_transform": draw(TRANSFORM)},
                )
            )
        elif kind == "sparse":
            edits.append(
                ("set", ("accessors", draw(st.integers(0, len(document["accessors"]) - 1)), "sparse"), draw(SPARSE))
            )
        else:  # what `matspray export` writes for `eval --glb`: the frame, the variant and the run
            key = draw(st.sampled_from(["frame", "variant", "run"]))
            value = draw(
                st.one_of(
                    VALUES,
                    st.sampled_from(["gltf", "dataset", "full", "no-prior", "bogus", "/nonexistent/run", "a\0b"]),
                )
            )
            edits.append(("set", ("asset", "extras", "matspray", key), value))

    def apply(copy: dict) -> dict:
        for kind, path, value in edits:
            try:
                parent = at(copy, path[:-1])
                if kind == "drop":
                    del parent[path[-1]]
                elif isinstance(parent, dict) or (isinstance(parent, list) and path[-1] < len(parent)):
                    parent[path[-1]] = value
            except (KeyError, IndexError, TypeError):  # an earlier edit removed or replaced the path
                pass
        return copy

    return apply


def accessor_bytes(document: dict, binary: bytearray, index: int) -> tuple[int, int, int]:
    """(offset in the binary chunk, count, item width in floats or ints) of one accessor of the intact file."""
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[accessor["type"]]
    return view.get("byteOffset", 0) + accessor.get("byteOffset", 0), accessor["count"], width


@st.composite
def value_edits(draw, document: dict, binary: bytes) -> bytes:
    """The binary chunk with values overwritten: NaN or Inf positions, normals or uvs; indices past the vertices."""
    out = bytearray(binary)
    for _ in range(draw(st.integers(1, 3))):
        index = draw(st.integers(0, len(document["accessors"]) - 1))
        offset, count, width = accessor_bytes(document, out, index)
        item = draw(st.integers(0, count * width - 1))
        if document["accessors"][index]["componentType"] == 5125:  # indices
            struct.pack_into("<I", out, offset + 4 * item, draw(st.sampled_from([3, 4, 5, 7, 255, 2**31, 2**32 - 1])))
        else:
            struct.pack_into("<f", out, offset + 4 * item, draw(st.sampled_from(SPECIALS)))
    return bytes(out)


def garbage_images():
    """Image bytes that are not a PNG or JPEG a texture may be: cut, garbage, other formats, odd modes."""
    from PIL import Image

    def encoded(mode: str, size, fmt: str, **kwargs) -> bytes:
        buffer = io.BytesIO()
        Image.new(mode, size).save(buffer, format=fmt, **kwargs)
        return buffer.getvalue()

    png = png_bytes(COLOUR)
    return st.sampled_from(
        [
            b"",
            b"\0" * 16,
            b"\x89PNG\r\n\x1a\n",
            png[:40],
            png[:-12],
            png[: len(png) // 2],
            b"GIF89a" + b"\0" * 20,
            encoded("RGB", (3, 2), "GIF"),
            encoded("RGB", (3, 2), "BMP"),
            encoded("RGB", (3, 2), "TIFF"),
            encoded("I;16", (3, 2), "PNG"),
            encoded("P", (3, 2), "PNG"),
            encoded("1", (3, 2), "PNG"),
            encoded("LA", (3, 2), "PNG"),
            encoded("CMYK", (3, 2), "JPEG"),
            encoded("RGB", (1, 1), "JPEG"),
            encoded("I", (3, 2), "TIFF"),
            encoded("F", (3, 2), "TIFF"),
        ]
    )


@st.composite
def image_edits(draw, document: dict, binary: bytes):
    """(document, binary) with image 0 or 1 replaced by other bytes, in the binary chunk or as a data URI."""
    import base64

    document = json.loads(json.dumps(document))
    index, data = draw(st.integers(0, 1)), draw(garbage_images())
    if draw(st.booleans()):
        document["images"][index] = {"uri": "data:image/png;base64," + base64.b64encode(data).decode()}
    else:
        start = len(binary) + (-len(binary) % 4)
        binary = binary + b"\0" * (start - len(binary)) + data
        document["bufferViews"].append({"buffer": 0, "byteOffset": start, "byteLength": len(data)})
        document["images"][index] = {"bufferView": len(document["bufferViews"]) - 1, "mimeType": "image/png"}
        document["buffers"][0]["byteLength"] = len(binary)
    return document, binary


@st.composite
def header_edits(draw, blob: bytes) -> bytes:
    """The magic, version, total length, a chunk length or a chunk type overwritten."""
    out = bytearray(blob)
    json_length = struct.unpack_from("<I", blob, 12)[0]
    fields = {
        "magic": 0,
        "version": 4,
        "length": 8,
        "json length": 12,
        "json type": 16,
        "bin length": 20 + json_length,
        "bin type": 24 + json_length,
    }
    offset = fields[draw(st.sampled_from(sorted(fields)))]
    value = draw(
        st.one_of(
            st.sampled_from(
                [
                    0,
                    1,
                    2,
                    3,
                    12,
                    19,
                    20,
                    2**31,
                    2**32 - 1,
                    len(blob) - 1,
                    len(blob) + 1,
                    0x46546C67,
                    0x4E4F534A,
                    0x004E4942,
                ]
            ),
            st.integers(0, 2**32 - 1),
        )
    )
    struct.pack_into("<I", out, offset, value)
    return bytes(out)


# ------------------------------------------------------------------------------------------ the properties
def check_asset(asset) -> None:
    """What a read asset promises synth and eval: finite placed meshes, indices inside, textures in [0, 1]."""
    assert asset.primitives
    for primitive in asset.primitives:
        count = len(primitive.positions)
        assert primitive.positions.shape == (count, 3) and np.isfinite(primitive.positions).all()
        assert primitive.indices.ndim == 2 and primitive.indices.shape[1] == 3 and len(primitive.indices)
        assert primitive.indices.min() >= 0 and primitive.indices.max() < count
        for uv in primitive.uvs:
            assert uv.shape == (count, 2)
        if primitive.normals is not None:
            assert primitive.normals.shape == (count, 3) and np.isfinite(primitive.normals).all()
        assert primitive.material is None or 0 <= primitive.material < len(asset.materials)
    for material in asset.materials:
        assert len(material.base_color_factor) == 4 and all(math.isfinite(c) for c in material.base_color_factor)
        assert math.isfinite(material.metallic_factor) and math.isfinite(material.roughness_factor)
        for texture in (material.base_color_texture, material.metallic_roughness_texture):
            if texture is not None:
                image = texture.image
                assert image.ndim == 3 and image.shape[0] >= 1 and image.shape[1] >= 1 and 1 <= image.shape[2] <= 4
                assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
                assert texture.wrap_s in ("repeat", "clamp", "mirror") and texture.wrap_t in (
                    "repeat",
                    "clamp",
                    "mirror",
                )
                assert np.isfinite(texture.transform.matrix()).all()


def check_parts(result) -> None:
    parts, textures, matrix = result
    assert np.isfinite(matrix).all() and len(parts) == len(textures) >= 1
    for part, texture in zip(parts, textures):
        assert np.isfinite(part.vertices).all() and np.isfinite(part.normals).all() and np.isfinite(part.uvs).all()
        assert part.faces.min() >= 0 and part.faces.max() < len(part.vertices)
        for values in (texture.base_color, texture.roughness, texture.metallic):
            assert np.isfinite(values).all() and values.min() >= 0 and values.max() <= 1


def read_everything(path: Path):
    """read_gltf, then the parts synth (fit) and eval --glb (keep, read_glb_parts) make of it."""
    asset = read_or_refuse(lambda: read_gltf(path), path, "read_gltf ")
    if asset is None:
        return None
    check_asset(asset)
    for placement in ("fit", "keep"):
        parts = read_or_refuse(lambda: asset_parts(asset, placement), path, f"asset_parts {placement} ")
        if parts is not None:
            check_parts(parts)
    glb_parts = read_or_refuse(lambda: read_glb_parts(path), path, "read_glb_parts ")
    if glb_parts is not None:
        parts, textures, extras = glb_parts
        check_parts((parts, textures, np.eye(4)))
        # a null run is no run (the reader then asks for --run and --data)
        assert extras.get("frame") in (None, "gltf", "dataset") and isinstance(extras.get("run") or "", str)
    return asset


def check_as_written(asset) -> None:
    assert [p.name for p in asset.primitives] == ["quad", "tetra"]
    for read, written in zip(asset.primitives, PRIMITIVES):
        np.testing.assert_allclose(read.positions, written.positions, atol=1e-6)
        np.testing.assert_array_equal(read.indices, written.indices)
    np.testing.assert_allclose(asset.materials[0].base_color_texture.image, COLOUR, atol=1e-6)
    np.testing.assert_allclose(asset.materials[0].metallic_roughness_texture.image, PACKED, atol=1e-6)
    assert asset.materials[1].base_color_factor == pytest.approx((0.2, 0.3, 0.4, 1.0)) and asset.extras == EXTRAS


@pytest.fixture(scope="module")
def intact():
    """(folder, the intact .glb's bytes, its document, its binary chunk)."""
    folder = Path(tempfile.mkdtemp(prefix="fuzz-glb-"))
    write_glb(folder / "intact.glb", PRIMITIVES, MATERIALS, extras=EXTRAS)
    document, binary = split((folder / "intact.glb").read_bytes())
    blob = pack(document, binary)  # the same file, its JSON as json.dumps writes it (what every corruption re-packs)
    (folder / "intact.glb").write_bytes(blob)
    return folder, blob, document, binary


def test_intact_glb_reads_as_written(intact):
    folder, *_ = intact
    asset = read_gltf(folder / "intact.glb")
    check_asset(asset)
    check_as_written(asset)
    check_parts(asset_parts(asset, "fit"))


@settings(FUZZ, max_examples=300)
@given(data=st.data())
def test_corrupted_glb(intact, data):
    folder, blob, document, binary = intact
    kind = data.draw(
        st.sampled_from(["bytes", "json bytes", "bin bytes", "header", "document", "document", "values", "image"]),
        label="kind",
    )
    json_end = 20 + struct.unpack_from("<I", blob, 12)[0]
    if kind == "bytes":  # anywhere, truncation included
        damaged_blob = damaged(blob, *data.draw(damage(len(blob))))
    elif kind in ("json bytes", "bin bytes"):  # flips inside one chunk's payload, the lengths intact
        low, high = (20, json_end) if kind == "json bytes" else (json_end + 8, len(blob))
        flips = data.draw(st.lists(st.tuples(st.integers(low, high - 1), st.integers(0, 255)), min_size=1, max_size=4))
        damaged_blob = damaged(blob, None, flips)
    elif kind == "header":
        damaged_blob = data.draw(header_edits(blob))
    elif kind == "document":
        damaged_blob = pack(data.draw(document_edits(document))(json.loads(json.dumps(document))), binary)
    elif kind == "values":
        damaged_blob = pack(document, data.draw(value_edits(document, binary)))
    else:
        damaged_blob = pack(*data.draw(image_edits(document, binary)))
    path = folder / "asset.glb"
    path.write_bytes(damaged_blob)
    asset = read_everything(path)
    if damaged_blob == blob:
        assert asset is not None
        check_as_written(asset)


@settings(FUZZ, max_examples=200)
@given(data=st.data())
def test_corrupted_gltf_with_external_bin(intact, data):
    """The same asset as a .gltf beside its .bin: the .bin missing, cut, padded or damaged, the document edited."""
    folder, blob, document, binary = intact
    gltf_folder = folder / "gltf"
    gltf_folder.mkdir(exist_ok=True)
    for old in gltf_folder.iterdir():
        old.unlink()
    external = json.loads(json.dumps(document))
    external["buffers"][0]["uri"] = "asset%20data.bin"  # a name with a space, URI-encoded as exporters write it
    kind = data.draw(st.sampled_from(["missing bin", "bin", "document", "intact"]), label="kind")
    payload = binary
    if kind == "bin":
        payload = damaged(binary, *data.draw(st.one_of(damage(len(binary)), st.just((None, [(0, 0)])))))
        payload += data.draw(st.sampled_from([b"", b"\0" * 4, b"x" * 1000]))
    elif kind == "document":
        external = data.draw(document_edits(external))(external)
    if kind != "missing bin":
        (gltf_folder / "asset data.bin").write_bytes(payload)
    path = gltf_folder / "asset.gltf"
    path.write_text(json.dumps(external))
    asset = read_everything(path)
    if kind == "missing bin":
        assert asset is None
    if kind == "intact":
        assert asset is not None
        check_as_written(asset)


# ------------------------------------------------------------------------------------------ the commands
@pytest.mark.parametrize("command", ["synth", "eval"])
def test_commands_refuse_a_damaged_glb_in_one_line(intact, tmp_path, capsys, command):
    """`matspray synth --asset` and `matspray eval --glb` on a .glb whose accessor reads past its buffer:
    exit 2, one line."""
    from matspray.cli import main

    folder, blob, document, binary = intact
    document = json.loads(json.dumps(document))
    document["accessors"][0]["count"] = 10**6
    path = tmp_path / "damaged.glb"
    path.write_bytes(pack(document, binary))
    if command == "synth":
        pytest.importorskip("mitsuba")
        argv = [
            "synth",
            "--asset",
            str(path),
            "--out",
            str(tmp_path / "object"),
            "--res",
            "16",
            "--views",
            "2",
            "--test-views",
            "1",
        ]
    else:
        argv = ["eval", "--glb", str(path), "--data", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "reads past" in err[0], err
    assert not (tmp_path / "object").exists()
