"""Gaussian splats as glTF 2.0 with the Khronos `KHR_gaussian_splatting` extension, and MatSpray's materials beside
them.

The extension as written in KhronosGroup/glTF's `extensions/2.0/Khronos/KHR_gaussian_splatting/README.md` at commit
63770cc (2026-04-15, status "Release Candidate"; SPLATS_DRAFT names it in every file): one POINTS primitive whose
attributes are POSITION, `KHR_gaussian_splatting:ROTATION` (unit quaternion, glTF's x y z w order),
`KHR_gaussian_splatting:SCALE` (linear), `KHR_gaussian_splatting:OPACITY` (after the sigmoid) and the spherical
harmonics `KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` (3DGS's coefficients: colour = sum + 0.5), kernel "ellipse",
colour space "srgb_rec709_display"; COLOR_0 carries the fallback colour of viewers that draw points.

What only MatSpray reads, as application-specific attributes (glTF: semantics starting with an underscore), 16-bit
normalised integers: `_BASECOLOR` (linear RGB), `_ROUGHNESS`, `_METALLIC` (unsigned) and `_NORMAL` (signed, unit);
and, in the primitive's `extras.matspray`, the estimated light as a FLOAT VEC3 accessor of its lat-long pixels.

Written and read here as plain JSON and bytes (no pygltflib): its Attributes type has no room for the extension's
names, and a GLB is two chunks.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matspray.data.images import atomic_target
from matspray.errors import file_error

EXTENSION = "KHR_gaussian_splatting"
SPLATS_DRAFT = "KhronosGroup/glTF extensions/2.0/Khronos/KHR_gaussian_splatting/README.md @ 63770cc (2026-04-15)"
PBR_ATTRIBUTES = ("_BASECOLOR", "_ROUGHNESS", "_METALLIC", "_NORMAL")
FLOAT, SHORT, UNSIGNED_SHORT, UNSIGNED_BYTE = 5126, 5122, 5123, 5121
ARRAY_BUFFER = 34962
COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
# quantised attributes: (numpy dtype, glTF component type, steps of one unit)
UNSIGNED_16 = (np.uint16, UNSIGNED_SHORT, 65535.0)
SIGNED_16 = (np.int16, SHORT, 32767.0)
HINT = "write it again with `matspray export --splats FILE.glb`"


@dataclass
class SplatFile:
    """What a splats glb holds, as arrays in the file's frame."""

    positions: np.ndarray  # [N, 3]
    rotations: np.ndarray  # [N, 4] unit quaternions (x, y, z, w), glTF's order
    scales: np.ndarray  # [N, 3] linear
    opacities: np.ndarray  # [N] in [0, 1]
    sh: np.ndarray  # [N, K, 3] 3DGS coefficients, K = (degree + 1)^2: colour = sum_k c_k Y_k(d) + 0.5
    base_color: np.ndarray | None = None  # [N, 3] linear, in [0, 1]
    roughness: np.ndarray | None = None  # [N]
    metallic: np.ndarray | None = None  # [N]
    normals: np.ndarray | None = None  # [N, 3] unit
    light: np.ndarray | None = None  # [H, 2H, 3] linear lat-long radiance (its frame: `extras`)
    extras: dict = field(default_factory=dict)  # the primitive's extras.matspray, besides the light

    @property
    def has_materials(self) -> bool:
        return all(v is not None for v in (self.base_color, self.roughness, self.metallic, self.normals))


def quantise(values: np.ndarray, kind) -> np.ndarray:
    dtype, _, steps = kind
    low = -1.0 if np.issubdtype(dtype, np.signedinteger) else 0.0
    return np.round(np.clip(values, low, 1.0) * steps).astype(dtype)


def dequantise(values: np.ndarray, kind) -> np.ndarray:  # glTF's normalised integers: max(c / steps, -1)
    return np.maximum(values.astype(np.float32) / np.float32(kind[2]), -1.0)


class _Builder:
    """The JSON document and the binary chunk being made; each accessor has its own bufferView, its elements
    4-byte aligned (glTF's rule for vertex attributes: a 16-bit VEC3 gets a stride of 8)."""

    def __init__(self):
        self.document = {"accessors": [], "bufferViews": []}
        self.data = bytearray()

    def accessor(
        self, values: np.ndarray, kind: str, component: int = FLOAT, normalized=False, bounds=False, vertex=True
    ) -> int:
        width = COMPONENTS[kind]
        array = np.ascontiguousarray(values).reshape(len(values), width)
        size = array.itemsize * width
        stride = -size % 4 + size
        rows = np.zeros((len(array), stride), dtype=np.uint8)
        rows[:, :size] = array.view(np.uint8).reshape(len(array), size)
        self.data.extend(b"\0" * (-len(self.data) % 4))
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": rows.size}
        if stride != size:
            view["byteStride"] = stride
        if vertex:
            view["target"] = ARRAY_BUFFER
        self.data.extend(rows.tobytes())
        self.document["bufferViews"].append(view)
        accessor = {"bufferView": len(self.document["bufferViews"]) - 1, "componentType": component}
        accessor.update(count=len(array), type=kind)
        if normalized:
            accessor["normalized"] = True
        if bounds:
            accessor["min"], accessor["max"] = array.min(0).tolist(), array.max(0).tolist()
        self.document["accessors"].append(accessor)
        return len(self.document["accessors"]) - 1


def sh_attribute(index: int) -> str:  # coefficient k = l^2 + l + m of 3DGS's order -> the extension's semantic
    degree = int(np.floor(np.sqrt(index)))
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{index - degree * degree}"


def write_splats_glb(path, splats: SplatFile, node_matrix: np.ndarray | None = None, asset_extras=None) -> None:
    """Write `splats` as one POINTS primitive with KHR_gaussian_splatting (and the materials when it has them) to
    `path`, atomically."""
    b = _Builder()
    f32 = lambda x: np.asarray(x, dtype=np.float32)  # noqa: E731
    colour = np.clip(splats.sh[:, 0] * 0.28209479177387814 + 0.5, 0.0, 1.0)  # sRGB display colour -> linear COLOR_0
    colour = np.where(colour <= 0.04045, colour / 12.92, ((colour + 0.055) / 1.055) ** 2.4)
    attributes = {
        "POSITION": b.accessor(f32(splats.positions), "VEC3", bounds=True),
        "COLOR_0": b.accessor(f32(np.concatenate([colour, splats.opacities[:, None]], 1)), "VEC4"),
        f"{EXTENSION}:ROTATION": b.accessor(f32(splats.rotations), "VEC4"),
        f"{EXTENSION}:SCALE": b.accessor(f32(splats.scales), "VEC3"),
        f"{EXTENSION}:OPACITY": b.accessor(f32(splats.opacities), "SCALAR"),
    }
    for k in range(splats.sh.shape[1]):
        attributes[sh_attribute(k)] = b.accessor(f32(splats.sh[:, k]), "VEC3")
    extras = dict(splats.extras)
    if splats.has_materials:
        for name, values, kind in (
            ("_BASECOLOR", splats.base_color, UNSIGNED_16),
            ("_ROUGHNESS", splats.roughness, UNSIGNED_16),
            ("_METALLIC", splats.metallic, UNSIGNED_16),
            ("_NORMAL", splats.normals, SIGNED_16),
        ):
            shape = "SCALAR" if values.ndim == 1 else "VEC3"
            attributes[name] = b.accessor(quantise(values, kind), shape, kind[1], normalized=True)
    if splats.light is not None:
        height = splats.light.shape[0]
        light = b.accessor(f32(splats.light.reshape(-1, 3)), "VEC3", vertex=False)
        extras["light"] = {"accessor": light, "height": height}
    primitive = {"attributes": attributes, "mode": 0}
    primitive["extensions"] = {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}
    primitive["extras"] = {"matspray": extras}
    node = {"mesh": 0, "name": "splats"}
    if node_matrix is not None:
        node["matrix"] = np.asarray(node_matrix, dtype=np.float64).T.reshape(-1).tolist()  # column-major
    b.data.extend(b"\0" * (-len(b.data) % 4))
    document = {
        "asset": {
            "version": "2.0",
            "generator": "matspray",
            "extras": {"splats_draft": SPLATS_DRAFT, **(asset_extras or {})},
        },
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"name": "splats", "primitives": [primitive]}],
        "buffers": [{"byteLength": len(b.data)}],
        **b.document,
    }
    write_glb_chunks(Path(path), document, bytes(b.data))


def write_glb_chunks(path: Path, document: dict, data: bytes) -> None:
    """A GLB: header, the JSON chunk (padded with spaces), the BIN chunk (padded with zeros); atomically."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    data += b"\0" * (-len(data) % 4)
    total = 12 + 8 + len(text) + 8 + len(data)
    blob = struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(text), 0x4E4F534A) + text
    blob += struct.pack("<II", len(data), 0x004E4942) + data
    write_bytes_atomic(path, blob)


def write_bytes_atomic(path: Path, blob: bytes) -> None:
    """Write `blob` to `path` whole or not at all (a reader never sees half a file), making the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    try:
        tmp.write_bytes(blob)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _read_chunks(path: Path) -> tuple[dict, bytes]:
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise file_error(path, f"cannot be read ({exc.strerror})") from None
    if len(blob) < 20 or blob[:4] != b"glTF":
        raise file_error(
            path, "is not a binary glTF (.glb) file", "pass the .glb that `matspray export --splats` wrote"
        )
    offset, document, data = 12, None, b""
    while offset + 8 <= len(blob):
        length, kind = struct.unpack_from("<II", blob, offset)
        chunk = blob[offset + 8 : offset + 8 + length]
        if kind == 0x4E4F534A:
            try:
                document = json.loads(chunk)
            except ValueError:
                raise file_error(path, "has a JSON chunk that is not valid JSON", HINT) from None
        elif kind == 0x004E4942:
            data = chunk
        offset += 8 + length + (-length % 4)
    if not isinstance(document, dict):
        raise file_error(path, "has no JSON chunk", HINT)
    return document, data


def _accessor(path: Path, document: dict, data: bytes, index) -> np.ndarray:  # -> [count, width] float32
    try:
        accessor = document["accessors"][index]
        view = document["bufferViews"][accessor["bufferView"]]
        width = COMPONENTS[accessor["type"]]
        dtype = {FLOAT: np.float32, SHORT: np.int16, UNSIGNED_SHORT: np.uint16, UNSIGNED_BYTE: np.uint8}[
            accessor["componentType"]
        ]
        count, size = accessor["count"], np.dtype(dtype).itemsize * width
        stride = view.get("byteStride", size)
        start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
        raw = np.frombuffer(data, dtype=np.uint8, count=(count - 1) * stride + size, offset=start)
    except (KeyError, IndexError, TypeError, ValueError):
        raise file_error(path, f"has a broken accessor {index}", HINT) from None
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, size), strides=(stride, 1))
    values = np.ascontiguousarray(rows).view(dtype).reshape(count, width)
    if accessor.get("normalized"):
        kind = SIGNED_16 if dtype == np.int16 else UNSIGNED_16 if dtype == np.uint16 else (dtype, 0, 255.0)
        return dequantise(values, kind)
    return values.astype(np.float32)


def read_splats_glb(path) -> tuple[SplatFile, np.ndarray]:
    """The first KHR_gaussian_splatting primitive of a .glb, and its node's matrix [4, 4] (identity when none)."""
    path = Path(path)
    document, data = _read_chunks(path)
    found = [
        (m, p)
        for m, mesh in enumerate(document.get("meshes", []))
        for p in mesh.get("primitives", [])
        if EXTENSION in p.get("extensions", {})
    ]
    if not found:
        raise file_error(path, f"holds no primitive with the {EXTENSION} extension", HINT)
    mesh_index, primitive = found[0]
    attributes = primitive["attributes"]
    missing = [
        name
        for name in ("POSITION", f"{EXTENSION}:ROTATION", f"{EXTENSION}:SCALE", f"{EXTENSION}:OPACITY", sh_attribute(0))
        if name not in attributes
    ]
    if missing:
        raise file_error(path, f"lacks the splat attributes {', '.join(missing)}", HINT)
    read = lambda name: _accessor(path, document, data, attributes[name])  # noqa: E731
    bases = 0
    while sh_attribute(bases) in attributes:
        bases += 1
    degree = int(np.floor(np.sqrt(bases))) - 1
    sh = np.stack([read(sh_attribute(k)) for k in range((degree + 1) ** 2)], axis=1)
    extras = dict(primitive.get("extras", {}).get("matspray", {}))
    light = None
    if "light" in extras:
        spec = extras.pop("light")
        height = int(spec["height"])
        light = _accessor(path, document, data, spec["accessor"]).reshape(height, 2 * height, 3)
    materials = {}
    if all(name in attributes for name in PBR_ATTRIBUTES):
        materials = {
            "base_color": read("_BASECOLOR"),
            "roughness": read("_ROUGHNESS")[:, 0],
            "metallic": read("_METALLIC")[:, 0],
            "normals": read("_NORMAL"),
        }
    splats = SplatFile(
        positions=read("POSITION"),
        rotations=read(f"{EXTENSION}:ROTATION"),
        scales=read(f"{EXTENSION}:SCALE"),
        opacities=read(f"{EXTENSION}:OPACITY")[:, 0],
        sh=sh,
        light=light,
        extras=extras,
        **materials,
    )
    counts = {len(v) for v in (splats.positions, splats.rotations, splats.scales, splats.opacities, splats.sh)}
    if len(counts) != 1:
        raise file_error(path, "has splat attributes of different lengths", HINT)
    for what, values in (("positions", splats.positions), ("scales", splats.scales), ("rotations", splats.rotations)):
        if not np.isfinite(values).all():
            raise file_error(path, f"has NaN or Inf {what}", HINT)
    matrix = np.eye(4)
    for node in document.get("nodes", []):
        if node.get("mesh") == mesh_index and "matrix" in node:
            matrix = np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    return splats, matrix


SPZ_EXTENSION = "KHR_gaussian_splatting_compression_spz_2"


def write_spz_glb(path, splats: SplatFile, spz: bytes) -> None:
    """The splats as KHR_gaussian_splatting with their data in one SPZ buffer (`spz`, what `export.splats.spz_bytes`
    makes of `splats`): the accessors say what the attributes are and hold no data, as CesiumJS reads them."""
    count = len(splats.positions)
    accessors = []

    def accessor(kind: str, component: int = FLOAT, **more) -> int:
        accessors.append({"componentType": component, "count": count, "type": kind, **more})
        return len(accessors) - 1

    bounds = {"min": splats.positions.min(0).tolist(), "max": splats.positions.max(0).tolist()}
    attributes = {
        "POSITION": accessor("VEC3", **bounds),
        "COLOR_0": accessor("VEC4", UNSIGNED_BYTE, normalized=True),
        f"{EXTENSION}:ROTATION": accessor("VEC4"),
        f"{EXTENSION}:SCALE": accessor("VEC3"),
        f"{EXTENSION}:OPACITY": accessor("SCALAR"),
    }
    for k in range(splats.sh.shape[1]):
        attributes[sh_attribute(k)] = accessor("VEC3")
    extension = {
        "kernel": "ellipse",
        "colorSpace": "srgb_rec709_display",
        "extensions": {SPZ_EXTENSION: {"bufferView": 0}},
    }
    document = {
        "asset": {"version": "2.0", "generator": "matspray", "extras": {"splats_draft": SPLATS_DRAFT}},
        "extensionsUsed": [EXTENSION, SPZ_EXTENSION],
        "extensionsRequired": [EXTENSION, SPZ_EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "splats"}],
        "meshes": [
            {
                "name": "splats",
                "primitives": [{"attributes": attributes, "mode": 0, "extensions": {EXTENSION: extension}}],
            }
        ],
        "buffers": [{"byteLength": len(spz) + (-len(spz) % 4)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(spz)}],
        "accessors": accessors,
    }
    write_glb_chunks(Path(path), document, spz)


def tileset(content: str, radius: float) -> dict:
    """A 3D Tiles 1.1 tileset of one glb `content` (a sphere of `radius` around the origin bounds it) whose glTF
    requires the two splat extensions: CesiumJS draws splats only from such a tileset."""
    gltf = {"extensionsUsed": [EXTENSION, SPZ_EXTENSION], "extensionsRequired": [EXTENSION, SPZ_EXTENSION]}
    return {
        "asset": {"version": "1.1"},
        "extensionsUsed": ["3DTILES_content_gltf"],
        "extensionsRequired": ["3DTILES_content_gltf"],
        "extensions": {"3DTILES_content_gltf": gltf},
        "geometricError": radius,
        "root": {
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, radius]},
            "geometricError": 0.0,
            "refine": "ADD",
            "content": {"uri": content},
        },
    }
