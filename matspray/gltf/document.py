"""The container and the JSON document of a glTF 2.0 file, checked before `read_gltf` reads it.

`split_glb` splits a .glb into its JSON and binary chunks, each checked against its stated length;
`load_document` reads a .glb or .gltf into pygltflib's typed model, after `check_document` has checked
every field `read_gltf` reads for its type and range, so that a damaged file is reported as one line
naming the file and the field instead of failing somewhere inside the reader.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

try:
    import pygltflib
except ImportError:  # optional: pip install 'matspray[gltf]'
    pygltflib = None

from matspray.errors import file_error

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


# ------------------------------------------------------------------------------------------ container
def split_glb(path: Path, data: bytes) -> tuple[str, bytes | None]:
    """The JSON text and binary chunk of a GLB file, each length checked against the bytes present."""
    if len(data) < 20:
        raise file_error(
            path,
            f"truncated .glb ({len(data)} bytes, shorter than its headers)",
            "the file is incomplete; copy or export it again",
        )
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC:
        raise file_error(path, "not a binary glTF (.glb) file: its first bytes are not 'glTF'")
    if version != 2:
        raise file_error(path, f"binary glTF version {version}; only glTF 2.0 is supported", "convert it to glTF 2.0")
    if length > len(data):
        raise file_error(
            path,
            f"truncated .glb: the header states {length} bytes, the file has {len(data)}",
            "the file is incomplete; copy or export it again",
        )
    chunks, offset = [], 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            raise file_error(
                path,
                f"truncated .glb: a chunk of {size} bytes runs past the end of the file",
                "the file is incomplete; copy or export it again",
            )
        chunks.append((kind, data[offset + 8 : offset + 8 + size]))
        offset += 8 + size
    if not chunks or chunks[0][0] != JSON_CHUNK:
        raise file_error(path, "malformed .glb: the first chunk is not the JSON chunk")
    binary = next((payload for kind, payload in chunks[1:] if kind == BIN_CHUNK), None)
    return chunks[0][1].decode("utf-8", errors="replace"), binary


def load_document(path: Path) -> tuple[pygltflib.GLTF2, bytes | None]:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise file_error(path, "no such file", "check the path") from None
    except OSError as exc:
        raise file_error(path, f"cannot be read ({exc.strerror or exc})") from None
    if path.suffix.lower() == ".glb" or data[:4] == b"glTF":
        text, binary = split_glb(path, data)
    elif path.suffix.lower() == ".gltf":
        text, binary = data.decode("utf-8", errors="replace"), None
    else:
        raise file_error(path, f"unknown asset type '{path.suffix}'", "give a .glb or .gltf file")
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise file_error(
            path, f"the glTF JSON does not parse ({exc.msg}, line {exc.lineno})", "the file is damaged or incomplete"
        ) from None
    asset = document.get("asset") if isinstance(document, dict) else None
    if not isinstance(asset, dict) or str(asset.get("version", "")).split(".")[0] != "2":
        raise file_error(path, "not a glTF 2.0 document (asset.version is not 2.x)", "convert it to glTF 2.0")
    check_document(path, document)
    try:
        gltf = pygltflib.GLTF2.from_json(json.dumps(document))
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        raise file_error(path, f"the glTF document does not follow the schema ({exc})") from None
    return gltf, binary


# ------------------------------------------------------------------------------------------ document
ARRAYS = (
    "scenes",
    "nodes",
    "meshes",
    "accessors",
    "bufferViews",
    "buffers",
    "images",
    "textures",
    "samplers",
    "materials",
)
DAMAGED = "the file is damaged or its exporter is broken; re-export it"


class DocumentCheck:
    """Types and ranges of the fields `read_gltf` reads, checked on the parsed JSON (pygltflib keeps whatever a field
    holds), so that a wrong one is one line naming the file and the field instead of an exception deep in the reader.
    A field that is absent or null takes the schema's default."""

    def __init__(self, path: Path, document: dict):
        self.path, self.document = path, document

    def fail(self, where: str, problem: str):
        raise file_error(self.path, f"{where} {problem}", DAMAGED)

    def objects(self, value, where: str) -> list:
        if value is None:
            return []
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            self.fail(where, "must be a list of objects")
        return value

    def object(self, value, where: str) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            self.fail(where, f"must be an object, not {json.dumps(value)[:40]}")
        return value

    def index(self, value, where: str, target: str, required: bool = False) -> None:
        count = len(self.document.get(target) or [])
        if value is None and not required:
            return
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
            self.fail(where, f"refers to {target}[{json.dumps(value)[:40]}], but the file has {count} {target}")

    def indices(self, value, where: str, target: str) -> None:
        if value is not None and not isinstance(value, list):
            self.fail(where, "must be a list of indices")
        for i, item in enumerate(value or []):
            self.index(item, f"{where}[{i}]", target, required=True)

    def whole(self, value, where: str, required: bool = False) -> None:
        if value is None and not required:
            return
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            self.fail(where, f"must be a whole number >= 0, got {json.dumps(value)[:40]}")

    def numbers(
        self, value, where: str, count: int | None = None
    ) -> None:  # one finite number (count None) or a list of `count`
        if value is None:
            return
        items = (
            value
            if count is not None and isinstance(value, list) and len(value) == count
            else [value]
            if count is None
            else None
        )
        if items is None or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in items
        ):
            shape = "a finite number" if count is None else f"a list of {count} finite numbers"
            self.fail(where, f"must be {shape}, got {json.dumps(value)[:60]}")

    def kind(self, value, where: str, kinds: tuple, what: str) -> None:
        if value is not None and (isinstance(value, bool) and bool not in kinds or not isinstance(value, kinds)):
            self.fail(where, f"must be {what}, got {json.dumps(value)[:40]}")

    def texture_info(self, value, where: str) -> None:
        info = self.object(value, where)
        if value is None:
            return
        self.index(info.get("index"), f"{where}.index", "textures", required=True)
        self.whole(info.get("texCoord"), f"{where}.texCoord")
        transform = self.object(
            self.object(info.get("extensions"), f"{where}.extensions").get("KHR_texture_transform"),
            f"{where}.extensions.KHR_texture_transform",
        )
        for name, count in (("offset", 2), ("rotation", None), ("scale", 2)):
            self.numbers(transform.get(name), f"{where}.extensions.KHR_texture_transform.{name}", count)
        self.whole(transform.get("texCoord"), f"{where}.extensions.KHR_texture_transform.texCoord")


def check_document(path: Path, document: dict) -> None:
    """Raises a DataError naming the file and the field when a field `read_gltf` reads has a wrong type or range."""
    c = DocumentCheck(path, document)
    for name in ARRAYS:
        c.objects(document.get(name), name)
    for name in ("extensionsUsed", "extensionsRequired"):
        value = document.get(name)
        if value is not None and (not isinstance(value, list) or not all(isinstance(v, str) for v in value)):
            c.fail(name, "must be a list of extension names")
    if document.get("scenes"):
        c.index(document.get("scene"), "scene", "scenes")
    for i, scene in enumerate(document.get("scenes") or []):
        c.indices(scene.get("nodes"), f"scenes[{i}].nodes", "nodes")
    for i, node in enumerate(document.get("nodes") or []):
        where = f"nodes[{i}]"
        c.indices(node.get("children"), f"{where}.children", "nodes")
        c.index(node.get("mesh"), f"{where}.mesh", "meshes")
        for name, count in (("matrix", 16), ("rotation", 4), ("scale", 3), ("translation", 3)):
            c.numbers(node.get(name), f"{where}.{name}", count)
    for i, mesh in enumerate(document.get("meshes") or []):
        for j, primitive in enumerate(c.objects(mesh.get("primitives"), f"meshes[{i}].primitives")):
            where = f"meshes[{i}].primitives[{j}]"
            attributes = c.object(primitive.get("attributes"), f"{where}.attributes")
            for name, value in attributes.items():
                if name in ("POSITION", "NORMAL") or name.startswith("TEXCOORD_"):
                    c.index(value, f"{where}.attributes.{name}", "accessors")
            c.index(primitive.get("indices"), f"{where}.indices", "accessors")
            c.index(primitive.get("material"), f"{where}.material", "materials")
            c.kind(primitive.get("mode"), f"{where}.mode", (int,), "a mode number")
    for i, accessor in enumerate(document.get("accessors") or []):
        where = f"accessors[{i}]"
        c.index(accessor.get("bufferView"), f"{where}.bufferView", "bufferViews")
        c.whole(accessor.get("byteOffset"), f"{where}.byteOffset")
        c.kind(accessor.get("componentType"), f"{where}.componentType", (int,), "a component type number")
        c.whole(accessor.get("count"), f"{where}.count", required=True)
        c.kind(accessor.get("type"), f"{where}.type", (str,), "SCALAR, VEC2, VEC3, VEC4, MAT2, MAT3 or MAT4")
        c.kind(accessor.get("normalized"), f"{where}.normalized", (bool,), "true or false")
        sparse = c.object(accessor.get("sparse"), f"{where}.sparse")
        if accessor.get("sparse") is not None:
            c.whole(sparse.get("count"), f"{where}.sparse.count", required=True)
            for part in ("indices", "values"):
                block = c.object(sparse.get(part), f"{where}.sparse.{part}")
                c.index(block.get("bufferView"), f"{where}.sparse.{part}.bufferView", "bufferViews", required=True)
                c.whole(block.get("byteOffset"), f"{where}.sparse.{part}.byteOffset")
            c.kind(
                c.object(sparse.get("indices"), "").get("componentType"),
                f"{where}.sparse.indices.componentType",
                (int,),
                "a component type number",
            )
    for i, view in enumerate(document.get("bufferViews") or []):
        where = f"bufferViews[{i}]"
        c.index(view.get("buffer"), f"{where}.buffer", "buffers", required=True)
        c.whole(view.get("byteOffset"), f"{where}.byteOffset")
        c.whole(view.get("byteLength"), f"{where}.byteLength", required=True)
        c.whole(view.get("byteStride"), f"{where}.byteStride")
    for i, buffer in enumerate(document.get("buffers") or []):
        c.kind(buffer.get("uri"), f"buffers[{i}].uri", (str,), "a URI")
        c.whole(buffer.get("byteLength"), f"buffers[{i}].byteLength")
    for i, image in enumerate(document.get("images") or []):
        c.kind(image.get("uri"), f"images[{i}].uri", (str,), "a URI")
        c.index(image.get("bufferView"), f"images[{i}].bufferView", "bufferViews")
    for i, texture in enumerate(document.get("textures") or []):
        c.index(texture.get("source"), f"textures[{i}].source", "images")
        c.index(texture.get("sampler"), f"textures[{i}].sampler", "samplers")
    for i, sampler in enumerate(document.get("samplers") or []):
        for name in ("wrapS", "wrapT"):
            c.kind(sampler.get(name), f"samplers[{i}].{name}", (int,), "a wrap mode number")
    for i, material in enumerate(document.get("materials") or []):
        where = f"materials[{i}]"
        pbr = c.object(material.get("pbrMetallicRoughness"), f"{where}.pbrMetallicRoughness")
        c.numbers(pbr.get("baseColorFactor"), f"{where}.pbrMetallicRoughness.baseColorFactor", 4)
        for name in ("metallicFactor", "roughnessFactor"):
            c.numbers(pbr.get(name), f"{where}.pbrMetallicRoughness.{name}")
        for name in ("baseColorTexture", "metallicRoughnessTexture"):
            c.texture_info(pbr.get(name), f"{where}.pbrMetallicRoughness.{name}")
        c.numbers(material.get("emissiveFactor"), f"{where}.emissiveFactor", 3)
        c.object(material.get("extensions"), f"{where}.extensions")
