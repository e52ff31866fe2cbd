"""`read_gltf`: a glTF 2.0 file (.glb, or .gltf with external or data-URI buffers and images) as plain arrays.

pygltflib parses the JSON document into its typed model (with the schema's defaults), once
`matspray.gltf.document` has checked the GLB chunks against their stated lengths and the fields read here;
the bytes are resolved here (buffers, strided and sparse accessors, normalised integers) so that every
problem is reported as one line naming the file. Every triangle primitive of the default scene is placed
by its node's transform through the hierarchy (TRS or matrix); points and lines are skipped, and what is
ignored is listed in `GltfAsset.notes`.
"""

from __future__ import annotations

import base64
import binascii
import io
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

try:
    import pygltflib
except ImportError:  # optional: pip install 'matspray[gltf]'
    pygltflib = None

from matspray.errors import file_error
from matspray.gaussians import quaternion_to_matrix
from matspray.gltf.document import DAMAGED, load_document
from matspray.gltf.model import (
    WRAP_MODES,
    GltfAsset,
    PbrMaterial,
    Primitive,
    TextureRef,
    TextureTransform,
    require_pygltflib,
)

SUPPORTED_REQUIRED = {"KHR_texture_transform", "KHR_mesh_quantization", "KHR_materials_emissive_strength"}
REEXPORT = (
    "re-export the asset with PNG/JPEG textures and uncompressed meshes (e.g. Blender's glTF exporter without Draco)"
)
COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
UNSIGNED = (5121, 5123, 5125)  # what indices may be
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN = 4, 5, 6
MODE_NAMES = {0: "points", 1: "lines", 2: "line loops", 3: "line strips"}


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
                return (
                    base64.b64decode(payload, validate=True)
                    if header.endswith(";base64")
                    else unquote(payload).encode("latin-1")
                )
            except (binascii.Error, ValueError):
                raise file_error(self.path, f"{what}: its data URI is not valid base64") from None
        target = self.path.parent / unquote(uri)
        try:
            return target.read_bytes()
        except OSError:
            raise file_error(
                self.path,
                f"{what} refers to the external file '{uri}', which is missing or unreadable ({target})",
                "keep the .gltf's files beside it, or use the .glb",
            ) from None

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
                raise file_error(
                    self.path,
                    f"buffer {index} holds {len(data)} bytes, {buffer.byteLength} stated (truncated)",
                    "the file is incomplete; copy or export it again",
                )
            self.buffers[index] = data
        return self.buffers[index]

    def view_bytes(self, index: int) -> tuple[bytes, int, int, int | None]:  # data, offset, length, stride
        view = self.gltf.bufferViews[index]
        data = self.buffer(view.buffer)
        offset = view.byteOffset or 0
        if offset + view.byteLength > len(data):
            raise file_error(
                self.path, f"bufferView {index} runs past the end of buffer {view.buffer} (truncated file?)"
            )
        return data, offset, view.byteLength, view.byteStride

    def typed(self, view: int | None, offset: int, dtype, count: int, width: int) -> np.ndarray:  # -> [count, width]
        if view is None:
            return np.zeros((count, width), dtype=dtype)
        data, start, length, stride = self.view_bytes(view)
        item = np.dtype(dtype).itemsize * width
        stride = stride or item
        if count and offset + stride * (count - 1) + item > length:
            raise file_error(
                self.path, f"an accessor of bufferView {view} reads past its end (truncated or malformed file)"
            )
        return np.ndarray(
            (count, width),
            dtype=np.dtype(dtype).newbyteorder("<"),
            buffer=data,
            offset=start + offset,
            strides=(stride, np.dtype(dtype).itemsize),
        ).copy()

    def accessor(
        self, index: int, use: str = "", types: tuple[str, ...] = (), components: tuple[int, ...] = ()
    ) -> np.ndarray:
        """Accessor `index` as [count, width] float64 (or integers for indices). `use` (e.g. 'POSITION of mesh 'a'')
        with `types` and `components`: the accessor types and component types that use allows."""
        accessor = self.gltf.accessors[index]
        dtype = COMPONENTS.get(accessor.componentType)
        if dtype is None or accessor.type not in WIDTHS:
            raise file_error(
                self.path, f"accessor {index} has an unknown component type {accessor.componentType} / {accessor.type}"
            )
        if types and accessor.type not in types or components and accessor.componentType not in components:
            raise file_error(
                self.path,
                f"accessor {index} ({accessor.type} of component type {accessor.componentType}) cannot be the {use} "
                f"(glTF allows {'/'.join(types)} of component types {', '.join(map(str, components or COMPONENTS))})",
                DAMAGED,
            )
        width = WIDTHS[accessor.type]
        values = self.typed(accessor.bufferView, accessor.byteOffset or 0, dtype, accessor.count, width)
        if accessor.sparse is not None and accessor.sparse.count:
            sparse = accessor.sparse
            if sparse.indices.componentType not in UNSIGNED:
                raise file_error(
                    self.path,
                    f"accessor {index}: sparse indices of component type {sparse.indices.componentType} "
                    f"(glTF allows {', '.join(map(str, UNSIGNED))})",
                    DAMAGED,
                )
            where = self.typed(
                sparse.indices.bufferView,
                sparse.indices.byteOffset or 0,
                COMPONENTS[sparse.indices.componentType],
                sparse.count,
                1,
            )[:, 0].astype(np.int64)
            if len(where) and where.max() >= accessor.count:
                raise file_error(
                    self.path, f"accessor {index}: a sparse index points past its {accessor.count} elements", DAMAGED
                )
            values[where] = self.typed(
                sparse.values.bufferView, sparse.values.byteOffset or 0, dtype, sparse.count, width
            )
        if accessor.normalized and dtype != np.float32:
            info = np.iinfo(dtype)
            return np.maximum(values.astype(np.float64) / info.max, -1.0)
        return values.astype(np.float64) if dtype == np.float32 else values.astype(np.int64)

    def image(self, index: int) -> np.ndarray:  # -> [H, W, C] float32 in [0, 1]
        if index not in self.images:
            image = self.gltf.images[index]
            if image.uri is not None:
                source, data = (
                    (image.uri if not image.uri.startswith("data:") else f"image {index}"),
                    self.uri_bytes(image.uri, f"image {index}"),
                )
            elif image.bufferView is not None:
                source = f"image {index}"
                raw, start, length, _ = self.view_bytes(image.bufferView)
                data = raw[start : start + length]
            else:
                raise file_error(self.path, f"image {index} has neither a uri nor a bufferView")
            self.images[index] = decode_image(self.path, source, data)
        return self.images[index]


def decode_image(path: Path, source: str, data: bytes) -> np.ndarray:  # -> [H, W, C] float32 in [0, 1]
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            if image.format not in ("PNG", "JPEG"):
                raise file_error(
                    path, f"{source} is a {image.format} image; glTF textures must be PNG or JPEG", REEXPORT
                )
            if image.mode in ("I;16", "I;16B", "I"):
                array = np.asarray(image, dtype=np.float64)[..., None] / 65535.0
            else:
                if image.mode not in ("L", "LA", "RGB", "RGBA"):
                    image = image.convert("RGBA")
                array = np.asarray(image, dtype=np.float64) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise file_error(
            path,
            f"{source} does not decode as a PNG or JPEG image ({exc})",
            "the image is damaged; re-export the asset",
        ) from None
    return (array[..., None] if array.ndim == 2 else array).astype(np.float32)


# ------------------------------------------------------------------------------------------ transforms
def node_matrix(node: pygltflib.Node) -> np.ndarray:  # -> [4, 4] local transform
    if node.matrix is not None:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF stores it column-major
    matrix = np.eye(4)
    x, y, z, w = node.rotation or [0, 0, 0, 1]  # glTF's order
    q = torch.tensor([w, x, y, z], dtype=torch.float64)
    rotation = quaternion_to_matrix(q / q.norm().clamp_min(1e-12)).numpy()
    matrix[:3, :3] = rotation @ np.diag(node.scale or [1, 1, 1])
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
        transform = TextureTransform(
            tuple(float(x) for x in given("offset", (0.0, 0.0))),
            float(given("rotation", 0.0)),
            tuple(float(x) for x in given("scale", (1.0, 1.0))),
        )
        tex_coord = given("texCoord", tex_coord)
    image = resolver.gltf.images[texture.source]
    source = image.uri if image.uri and not image.uri.startswith("data:") else f"image {texture.source}"
    return TextureRef(resolver.image(texture.source), int(tex_coord), transform, wraps[0], wraps[1], source)


def read_material(resolver: Resolver, material: pygltflib.Material, notes: set[str]) -> PbrMaterial:
    for what, present in (
        ("normal textures", material.normalTexture),
        ("occlusion textures", material.occlusionTexture),
        ("emissive textures", material.emissiveTexture),
        ("emissive factors", material.emissiveFactor and any(material.emissiveFactor)),
        (f"alpha mode {material.alphaMode}", material.alphaMode not in (None, "OPAQUE")),
    ):
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
        raise file_error(
            resolver.path,
            f"mesh '{name}': a vertex position is not finite (NaN or infinity)",
            "fix or re-export the mesh",
        )
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
            raise file_error(
                resolver.path,
                f"mesh '{name}': a vertex normal is not finite (NaN or infinity)",
                "fix or re-export the mesh",
            )
        # by the inverse transpose, as the cofactor matrix (det x inverse transpose), which a flattening scale of 0
        # also has
        cofactor = np.stack(
            [
                np.cross(linear[:, 1], linear[:, 2]),
                np.cross(linear[:, 2], linear[:, 0]),
                np.cross(linear[:, 0], linear[:, 1]),
            ],
            axis=1,
        )
        normals = normals @ cofactor.T * (-1.0 if np.linalg.det(linear) < 0 else 1.0)
        length = np.linalg.norm(normals, axis=-1, keepdims=True)
        if not (np.isfinite(length) & (length > 1e-12)).all():
            raise file_error(
                resolver.path,
                f"mesh '{name}': a vertex normal is zero (or its node's transform makes it so)",
                "fix or re-export the mesh",
            )
        normals /= length
    if np.linalg.det(linear) < 0:  # a mirroring transform turns the front faces around
        faces = faces[:, [0, 2, 1]]
    uvs = []
    while (uv := attribute(primitive.attributes, f"TEXCOORD_{len(uvs)}")) is not None:
        uvs.append(resolver.accessor(uv, f"TEXCOORD_{len(uvs)} of mesh '{name}'", ("VEC2",)))
        if len(uvs[-1]) != count:
            raise file_error(
                resolver.path,
                f"mesh '{name}': {len(uvs[-1])} TEXCOORD_{len(uvs) - 1} values for {count} vertices",
                DAMAGED,
            )
    if not np.isfinite(placed).all():
        raise file_error(
            resolver.path, f"mesh '{name}': a transformed vertex position is not finite", "fix the node transforms"
        )
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
        raise file_error(
            path,
            f"requires the glTF extension{'s' if len(unsupported) > 1 else ''} {', '.join(unsupported)}, "
            "which matspray cannot read",
            REEXPORT,
        )
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
                    raise file_error(
                        path, f"mesh '{name}' uses material {read.material}, but the file has {len(materials)}"
                    )
                primitives.append(read)
    if not primitives:
        raise file_error(path, "the default scene has no triangles", "export the asset with its meshes as triangles")
    extras = gltf.asset.extras if isinstance(gltf.asset.extras, dict) else {}
    return GltfAsset(str(path), primitives, materials, sorted(notes), extras)
