"""`read_gltf`: a glTF 2.0 file (.glb, or .gltf with external or data-URI buffers and images) as plain arrays.

pygltflib parses the JSON document into its typed model (with the schema's defaults); the bytes are
resolved here (GLB chunks checked against their stated lengths, buffers, strided and sparse accessors,
normalised integers) so that every problem is reported as one line naming the file. Every triangle
primitive of the default scene is placed by its node's transform through the hierarchy (TRS or matrix);
points and lines are skipped, and what is ignored is listed in `GltfAsset.notes`.
"""

from __future__ import annotations

import base64
import binascii
import io
import json
import math
import struct
from pathlib import Path
from urllib.parse import unquote

import numpy as np
from PIL import Image, UnidentifiedImageError

try:
    import pygltflib
except ImportError:  # optional: pip install 'matspray[gltf]'
    pygltflib = None

from matspray.errors import file_error
from matspray.gltf.model import WRAP_MODES, GltfAsset, PbrMaterial, Primitive, TextureRef, TextureTransform, require_pygltflib

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
SUPPORTED_REQUIRED = {"KHR_texture_transform", "KHR_mesh_quantization", "KHR_materials_emissive_strength"}
REEXPORT = "re-export the asset with PNG/JPEG textures and uncompressed meshes (e.g. Blender's glTF exporter without Draco)"
COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
UNSIGNED = (5121, 5123, 5125)  # what indices may be
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN = 4, 5, 6
MODE_NAMES = {0: "points", 1: "lines", 2: "line loops", 3: "line strips"}


# ------------------------------------------------------------------------------------------ container
def split_glb(path: Path, data: bytes) -> tuple[str, bytes | None]:
    """The JSON text and binary chunk of a GLB file, each length checked against the bytes present."""
    if len(data) < 20:
        raise file_error(path, f"truncated .glb ({len(data)} bytes, shorter than its headers)", "the file is incomplete; copy or export it again")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC:
        raise file_error(path, "not a binary glTF (.glb) file: its first bytes are not 'glTF'")
    if version != 2:
        raise file_error(path, f"binary glTF version {version}; only glTF 2.0 is supported", "convert it to glTF 2.0")
    if length > len(data):
        raise file_error(path, f"truncated .glb: the header states {length} bytes, the file has {len(data)}", "the file is incomplete; copy or export it again")
    chunks, offset = [], 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            raise file_error(path, f"truncated .glb: a chunk of {size} bytes runs past the end of the file", "the file is incomplete; copy or export it again")
        chunks.append((kind, data[offset + 8: offset + 8 + size]))
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
        raise file_error(path, f"the glTF JSON does not parse ({exc.msg}, line {exc.lineno})", "the file is damaged or incomplete") from None
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
ARRAYS = ("scenes", "nodes", "meshes", "accessors", "bufferViews", "buffers", "images", "textures", "samplers", "materials")
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

    def numbers(self, value, where: str, count: int | None = None) -> None:  # one finite number (count None) or a list of `count`
        if value is None:
            return
        items = value if count is not None and isinstance(value, list) and len(value) == count else [value] if count is None else None
        if items is None or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in items):
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
        transform = self.object(self.object(info.get("extensions"), f"{where}.extensions").get("KHR_texture_transform"),
                                f"{where}.extensions.KHR_texture_transform")
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
            c.kind(c.object(sparse.get("indices"), "").get("componentType"), f"{where}.sparse.indices.componentType", (int,),
                   "a component type number")
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


# ------------------------------------------------------------------------------------------ bytes
class Resolver:
    """Buffers, accessors and images of one document, read lazily and cached."""

    def __init__(self, path: Path, gltf: pygltflib.GLTF2, binary: bytes | None):
        self.path, self.gltf, self.binary = path, gltf, binary
        self.buffers: dict[int, bytes] = {}
        self.images: dict[int, np.ndarray] = {}

    def uri_bytes(self, uri: str, what: str) -> bytes:
        if uri.startswith("data:"):
            header, _, payload = uri.partition(",")
            try:
                return base64.b64decode(payload, validate=True) if header.endswith(";base64") else unquote(payload).encode("latin-1")
            except (binascii.Error, ValueError):
                raise file_error(self.path, f"{what}: its data URI is not valid base64") from None
        target = self.path.parent / unquote(uri)
        try:
            return target.read_bytes()
        except OSError:
            raise file_error(self.path, f"{what} refers to the external file '{uri}', which is missing or unreadable ({target})",
                             "keep the .gltf's files beside it, or use the .glb") from None

    def buffer(self, index: int) -> bytes:
        if index not in self.buffers:
            buffer = self.gltf.buffers[index]
            if buffer.uri is None:
                if self.binary is None:
                    raise file_error(self.path, f"buffer {index} has no uri and there is no binary chunk")
                data = self.binary
            else:
                data = self.uri_bytes(buffer.uri, f"buffer {index}")
            if buffer.byteLength is not None and len(data) < buffer.byteLength:
                raise file_error(self.path, f"buffer {index} holds {len(data)} bytes, {buffer.byteLength} stated (truncated)",
                                 "the file is incomplete; copy or export it again")
            self.buffers[index] = data
        return self.buffers[index]

    def view_bytes(self, index: int) -> tuple[bytes, int, int, int | None]:  # data, offset, length, stride
        view = self.gltf.bufferViews[index]
        data = self.buffer(view.buffer)
        offset = view.byteOffset or 0
        if offset + view.byteLength > len(data):
            raise file_error(self.path, f"bufferView {index} runs past the end of buffer {view.buffer} (truncated file?)")
        return data, offset, view.byteLength, view.byteStride

    def typed(self, view: int | None, offset: int, dtype, count: int, width: int) -> np.ndarray:  # -> [count, width]
        if view is None:
            return np.zeros((count, width), dtype=dtype)
        data, start, length, stride = self.view_bytes(view)
        item = np.dtype(dtype).itemsize * width
        stride = stride or item
        if count and offset + stride * (count - 1) + item > length:
            raise file_error(self.path, f"an accessor of bufferView {view} reads past its end (truncated or malformed file)")
        return np.ndarray((count, width), dtype=np.dtype(dtype).newbyteorder("<"), buffer=data,
                          offset=start + offset, strides=(stride, np.dtype(dtype).itemsize)).copy()

    def accessor(self, index: int, use: str = "", types: tuple[str, ...] = (), components: tuple[int, ...] = ()) -> np.ndarray:
        """Accessor `index` as [count, width] float64 (or integers for indices). `use` (e.g. 'POSITION of mesh 'a'')
        with `types` and `components`: the accessor types and component types that use allows."""
        accessor = self.gltf.accessors[index]
        dtype = COMPONENTS.get(accessor.componentType)
        if dtype is None or accessor.type not in WIDTHS:
            raise file_error(self.path, f"accessor {index} has an unknown component type {accessor.componentType} / {accessor.type}")
        if types and accessor.type not in types or components and accessor.componentType not in components:
            raise file_error(self.path, f"accessor {index} ({accessor.type} of component type {accessor.componentType}) cannot be the {use} "
                                        f"(glTF allows {'/'.join(types)} of component types {', '.join(map(str, components or COMPONENTS))})",
                             DAMAGED)
        width = WIDTHS[accessor.type]
        values = self.typed(accessor.bufferView, accessor.byteOffset or 0, dtype, accessor.count, width)
        if accessor.sparse is not None and accessor.sparse.count:
            sparse = accessor.sparse
            if sparse.indices.componentType not in UNSIGNED:
                raise file_error(self.path, f"accessor {index}: sparse indices of component type {sparse.indices.componentType} "
                                            f"(glTF allows {', '.join(map(str, UNSIGNED))})", DAMAGED)
            where = self.typed(sparse.indices.bufferView, sparse.indices.byteOffset or 0,
                               COMPONENTS[sparse.indices.componentType], sparse.count, 1)[:, 0].astype(np.int64)
            if len(where) and where.max() >= accessor.count:
                raise file_error(self.path, f"accessor {index}: a sparse index points past its {accessor.count} elements", DAMAGED)
            values[where] = self.typed(sparse.values.bufferView, sparse.values.byteOffset or 0, dtype, sparse.count, width)
        if accessor.normalized and dtype != np.float32:
            info = np.iinfo(dtype)
            return np.maximum(values.astype(np.float64) / info.max, -1.0)
        return values.astype(np.float64) if dtype == np.float32 else values.astype(np.int64)

    def image(self, index: int) -> np.ndarray:  # -> [H, W, C] float32 in [0, 1]
        if index not in self.images:
            image = self.gltf.images[index]
            if image.uri is not None:
                source, data = (image.uri if not image.uri.startswith("data:") else f"image {index}"), self.uri_bytes(image.uri, f"image {index}")
            elif image.bufferView is not None:
                source = f"image {index}"
                raw, start, length, _ = self.view_bytes(image.bufferView)
                data = raw[start:start + length]
            else:
                raise file_error(self.path, f"image {index} has neither a uri nor a bufferView")
            self.images[index] = decode_image(self.path, source, data)
        return self.images[index]


def decode_image(path: Path, source: str, data: bytes) -> np.ndarray:  # -> [H, W, C] float32 in [0, 1]
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            if image.format not in ("PNG", "JPEG"):
                raise file_error(path, f"{source} is a {image.format} image; glTF textures must be PNG or JPEG", REEXPORT)
            if image.mode in ("I;16", "I;16B", "I"):
                array = np.asarray(image, dtype=np.float64)[..., None] / 65535.0
            else:
                if image.mode not in ("L", "LA", "RGB", "RGBA"):
                    image = image.convert("RGBA")
                array = np.asarray(image, dtype=np.float64) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise file_error(path, f"{source} does not decode as a PNG or JPEG image ({exc})", "the image is damaged; re-export the asset") from None
    return (array[..., None] if array.ndim == 2 else array).astype(np.float32)


# ------------------------------------------------------------------------------------------ transforms
def quaternion_matrix(q) -> np.ndarray:  # [x, y, z, w] -> [3, 3]
    x, y, z, w = np.asarray(q, dtype=np.float64) / max(np.linalg.norm(q), 1e-12)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def node_matrix(node: pygltflib.Node) -> np.ndarray:  # -> [4, 4] local transform
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores it column-major
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(node.rotation or [0, 0, 0, 1]) @ np.diag(node.scale or [1, 1, 1])
    matrix[:3, 3] = node.translation or [0, 0, 0]
    return matrix


def scene_nodes(path: Path, gltf: pygltflib.GLTF2):
    """(node index, world matrix [4, 4]) of every node of the default scene (all root nodes without scenes)."""
    if gltf.scenes:
        roots = gltf.scenes[gltf.scene or 0].nodes or []
    else:
        children = {c for node in gltf.nodes for c in (node.children or [])}
        roots = [i for i in range(len(gltf.nodes)) if i not in children]
    stack = [(root, np.eye(4), 0) for root in reversed(roots)]  # depth first, in document order
    while stack:
        index, parent, depth = stack.pop()
        if depth > len(gltf.nodes):
            raise file_error(path, "the node hierarchy has a cycle")
        world = parent @ node_matrix(gltf.nodes[index])
        yield index, world
        stack.extend((child, world, depth + 1) for child in reversed(gltf.nodes[index].children or []))


def triangles(indices: np.ndarray, mode: int) -> np.ndarray:  # [N] -> [F, 3]
    if mode == TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    i = np.arange(max(len(indices) - 2, 0))
    if mode == TRIANGLE_STRIP:  # every other triangle is flipped back to a consistent winding
        odd = i % 2
        return np.stack([indices[i], indices[i + 1 + odd], indices[i + 2 - odd]], axis=-1)
    return np.stack([indices[i + 1], indices[i + 2], np.full_like(i, indices[0])], axis=-1)  # fan


# ------------------------------------------------------------------------------------------ materials
def texture_ref(resolver: Resolver, info, notes: set[str]) -> TextureRef | None:
    if info is None or info.index is None:
        return None
    gltf = resolver.gltf
    texture = gltf.textures[info.index]
    for name in texture.extensions or {}:
        notes.add(f"texture extension {name} (its fallback image is used)")
    if texture.source is None:
        raise file_error(resolver.path, f"texture {info.index} has no PNG/JPEG source image", REEXPORT)
    sampler = gltf.samplers[texture.sampler] if texture.sampler is not None else pygltflib.Sampler()
    wraps = []
    for axis, enum in (("S", sampler.wrapS), ("T", sampler.wrapT)):
        mode = WRAP_MODES.get(10497 if enum is None else enum)
        if mode is None:
            raise file_error(resolver.path, f"sampler of texture {info.index}: unknown wrap{axis} {enum}")
        wraps.append(mode)
    tex_coord, transform = info.texCoord or 0, TextureTransform()
    extension = (info.extensions or {}).get("KHR_texture_transform")
    if extension:
        given = lambda name, default: default if extension.get(name) is None else extension[name]  # noqa: E731 - null: the default
        transform = TextureTransform(tuple(float(x) for x in given("offset", (0.0, 0.0))), float(given("rotation", 0.0)),
                                     tuple(float(x) for x in given("scale", (1.0, 1.0))))
        tex_coord = given("texCoord", tex_coord)
    image = resolver.gltf.images[texture.source]
    source = image.uri if image.uri and not image.uri.startswith("data:") else f"image {texture.source}"
    return TextureRef(resolver.image(texture.source), int(tex_coord), transform, wraps[0], wraps[1], source)


def read_material(resolver: Resolver, material: pygltflib.Material, notes: set[str]) -> PbrMaterial:
    for what, present in (("normal textures", material.normalTexture), ("occlusion textures", material.occlusionTexture),
                          ("emissive textures", material.emissiveTexture),
                          ("emissive factors", material.emissiveFactor and any(material.emissiveFactor)),
                          (f"alpha mode {material.alphaMode}", material.alphaMode not in (None, "OPAQUE"))):
        if present:
            notes.add(what)
    for name in material.extensions or {}:
        notes.add(f"extension {name}")
    pbr = material.pbrMetallicRoughness or pygltflib.PbrMetallicRoughness()
    factor = tuple(float(c) for c in (pbr.baseColorFactor or [1.0, 1.0, 1.0, 1.0]))
    if factor[3] < 1.0:
        notes.add("base colour alpha")
    return PbrMaterial(
        name=material.name or "",
        base_color_factor=factor,
        metallic_factor=float(1.0 if pbr.metallicFactor is None else pbr.metallicFactor),
        roughness_factor=float(1.0 if pbr.roughnessFactor is None else pbr.roughnessFactor),
        base_color_texture=texture_ref(resolver, pbr.baseColorTexture, notes),
        metallic_roughness_texture=texture_ref(resolver, pbr.metallicRoughnessTexture, notes),
        double_sided=bool(material.doubleSided),
    )


# ------------------------------------------------------------------------------------------ primitives
def attribute(attributes, name: str):
    value = getattr(attributes, name, None)
    if value is None and isinstance(getattr(attributes, "__dict__", None), dict):
        value = attributes.__dict__.get(name)
    return value


def read_primitive(resolver: Resolver, name: str, primitive, world: np.ndarray, notes: set[str]) -> Primitive | None:
    mode = TRIANGLES if primitive.mode is None else primitive.mode
    if mode not in (TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN):
        notes.add(f"{MODE_NAMES.get(mode, f'mode {mode}')} primitives (skipped)")
        return None
    if primitive.targets:
        notes.add("morph targets (the base mesh is used)")
    position = attribute(primitive.attributes, "POSITION")
    if position is None:
        raise file_error(resolver.path, f"mesh '{name}': a triangle primitive has no POSITION attribute")
    positions = resolver.accessor(position, f"POSITION of mesh '{name}'", ("VEC3",))
    if not np.isfinite(positions).all():
        raise file_error(resolver.path, f"mesh '{name}': a vertex position is not finite (NaN or infinity)", "fix or re-export the mesh")
    count = len(positions)
    if primitive.indices is not None:
        indices = resolver.accessor(primitive.indices, f"indices of mesh '{name}'", ("SCALAR",), UNSIGNED)[:, 0]
    else:
        indices = np.arange(count)
    if len(indices) and (indices.min() < 0 or indices.max() >= count):
        raise file_error(resolver.path, f"mesh '{name}': an index points past its {count} vertices")
    faces = triangles(indices.astype(np.int64), mode)
    if len(faces) == 0:
        return None
    linear, offset = world[:3, :3], world[:3, 3]
    placed = positions @ linear.T + offset
    normals = None
    if attribute(primitive.attributes, "NORMAL") is not None:
        normals = resolver.accessor(attribute(primitive.attributes, "NORMAL"), f"NORMAL of mesh '{name}'", ("VEC3",))
        if len(normals) != count:
            raise file_error(resolver.path, f"mesh '{name}': {len(normals)} normals for {count} vertices", DAMAGED)
        if not np.isfinite(normals).all():
            raise file_error(resolver.path, f"mesh '{name}': a vertex normal is not finite (NaN or infinity)", "fix or re-export the mesh")
        # by the inverse transpose, as the cofactor matrix (det x inverse transpose), which a flattening scale of 0 also has
        cofactor = np.stack([np.cross(linear[:, 1], linear[:, 2]), np.cross(linear[:, 2], linear[:, 0]),
                             np.cross(linear[:, 0], linear[:, 1])], axis=1)
        normals = normals @ cofactor.T * (-1.0 if np.linalg.det(linear) < 0 else 1.0)
        length = np.linalg.norm(normals, axis=-1, keepdims=True)
        if not (np.isfinite(length) & (length > 1e-12)).all():
            raise file_error(resolver.path, f"mesh '{name}': a vertex normal is zero (or its node's transform makes it so)",
                             "fix or re-export the mesh")
        normals /= length
    if np.linalg.det(linear) < 0:  # a mirroring transform turns the front faces around
        faces = faces[:, [0, 2, 1]]
    uvs = []
    while (uv := attribute(primitive.attributes, f"TEXCOORD_{len(uvs)}")) is not None:
        uvs.append(resolver.accessor(uv, f"TEXCOORD_{len(uvs)} of mesh '{name}'", ("VEC2",)))
        if len(uvs[-1]) != count:
            raise file_error(resolver.path, f"mesh '{name}': {len(uvs[-1])} TEXCOORD_{len(uvs) - 1} values for {count} vertices", DAMAGED)
    if not np.isfinite(placed).all():
        raise file_error(resolver.path, f"mesh '{name}': a transformed vertex position is not finite", "fix the node transforms")
    return Primitive(name, placed, faces, tuple(uvs), normals, primitive.material)


def read_gltf(path) -> GltfAsset:
    """Every triangle primitive of the default scene of `path`, its materials and decoded textures.

    Raises DataError (one line naming the file) on a required extension we cannot read, a truncated
    file, a missing external file, an image that does not decode, no triangles, or a non-finite vertex."""
    require_pygltflib(pygltflib)
    path = Path(path)
    gltf, binary = load_document(path)
    unsupported = [name for name in gltf.extensionsRequired or [] if name not in SUPPORTED_REQUIRED]
    if unsupported:
        raise file_error(path, f"requires the glTF extension{'s' if len(unsupported) > 1 else ''} {', '.join(unsupported)}, "
                               "which matspray cannot read", REEXPORT)
    notes = {f"extension {name}" for name in gltf.extensionsUsed or [] if name not in SUPPORTED_REQUIRED}
    resolver = Resolver(path, gltf, binary)
    materials = [read_material(resolver, material, notes) for material in gltf.materials]
    primitives = []
    for node_index, world in scene_nodes(path, gltf):
        node = gltf.nodes[node_index]
        if node.mesh is None:
            continue
        if node.skin is not None:
            notes.add("skins (the bind pose is used)")
        mesh = gltf.meshes[node.mesh]
        base = mesh.name or node.name or f"mesh {node.mesh}"
        for number, primitive in enumerate(mesh.primitives):
            name = base if len(mesh.primitives) == 1 else f"{base}/{number}"
            read = read_primitive(resolver, name, primitive, world, notes)
            if read is not None:
                if read.material is not None and not 0 <= read.material < len(materials):
                    raise file_error(path, f"mesh '{name}' uses material {read.material}, but the file has {len(materials)}")
                primitives.append(read)
    if not primitives:
        raise file_error(path, "the default scene has no triangles", "export the asset with its meshes as triangles")
    extras = gltf.asset.extras if isinstance(gltf.asset.extras, dict) else {}
    return GltfAsset(str(path), primitives, materials, sorted(notes), extras)
