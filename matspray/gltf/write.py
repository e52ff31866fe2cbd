"""`write_glb`: triangle meshes and metallic-roughness materials (with textures) to one binary glTF file.

pygltflib holds the document; the binary chunk (vertex data and PNG images, each 4-byte aligned) is
assembled here. Textures are written as 8-bit PNGs of the values given (encode a base colour to sRGB
before, e.g. with `encode_base_color`); a non-identity KHR_texture_transform is written as the extension.
The file is written atomically: a temporary sibling renamed into place.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
from PIL import Image

try:
    import pygltflib
except ImportError:  # optional: pip install 'matspray[gltf]'
    pygltflib = None

from matspray.data.images import atomic_target
from matspray.errors import ConfigError
from matspray.gltf.model import WRAP_ENUMS, PbrMaterial, Primitive, TextureRef, require_pygltflib

FLOAT, UINT32 = 5126, 5125  # glTF component types
TRANSFORM_EXTENSION = "KHR_texture_transform"


def encode_base_color(linear: np.ndarray) -> np.ndarray:  # [..., C] linear -> [..., C] sRGB-encoded, in [0, 1]
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 1e-12) ** (1.0 / 2.4) - 0.055)


def pack_metallic_roughness(roughness: np.ndarray, metallic: np.ndarray) -> np.ndarray:  # [H, W] x2 -> [H, W, 3]
    """glTF's metallicRoughnessTexture layout: G = roughness, B = metallic (R, occlusion, left 0)."""
    return np.stack([np.zeros_like(roughness), roughness, metallic], axis=-1)


def png_bytes(values: np.ndarray) -> bytes:  # [H, W, C] in [0, 1] -> 8-bit PNG
    array = np.asarray(values, dtype=np.float64)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4) or not np.isfinite(array).all():
        raise ConfigError(f"a glTF texture must be a finite [H, W, 1|3|4] array, got shape {array.shape}")
    quantised = np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(quantised[..., 0] if quantised.shape[2] == 1 else quantised).save(buffer, format="PNG")
    return buffer.getvalue()


class _Blob:
    """The binary chunk under construction: each piece is 4-byte aligned and gets its own bufferView."""

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf, self.data = gltf, bytearray()

    def view(self, payload: bytes, target: int | None = None) -> int:
        self.data.extend(b"\0" * (-len(self.data) % 4))
        self.gltf.bufferViews.append(
            pygltflib.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(payload), target=target)
        )
        self.data.extend(payload)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, values: np.ndarray, kind: str, bounds: bool = False) -> int:
        is_index = kind == pygltflib.SCALAR
        array = np.ascontiguousarray(values, dtype=np.uint32 if is_index else np.float32)
        target = pygltflib.ELEMENT_ARRAY_BUFFER if is_index else pygltflib.ARRAY_BUFFER
        view = self.view(array.tobytes(), target)
        flat = array.reshape(len(array), -1) if not is_index else array.reshape(-1, 1)
        accessor = pygltflib.Accessor(
            bufferView=view, componentType=UINT32 if is_index else FLOAT, count=len(flat), type=kind
        )
        if bounds:
            accessor.min, accessor.max = flat.min(0).tolist(), flat.max(0).tolist()
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1


def _texture_info(gltf: pygltflib.GLTF2, blob: _Blob, texture: TextureRef) -> pygltflib.TextureInfo:
    for wrap in (texture.wrap_s, texture.wrap_t):
        if wrap not in WRAP_ENUMS:
            raise ConfigError(f"unknown texture wrap mode '{wrap}' (valid: {', '.join(WRAP_ENUMS)})")
    gltf.images.append(pygltflib.Image(bufferView=blob.view(png_bytes(texture.image)), mimeType="image/png"))
    gltf.samplers.append(
        pygltflib.Sampler(
            magFilter=pygltflib.LINEAR,
            minFilter=pygltflib.LINEAR,
            wrapS=WRAP_ENUMS[texture.wrap_s],
            wrapT=WRAP_ENUMS[texture.wrap_t],
        )
    )
    gltf.textures.append(pygltflib.Texture(source=len(gltf.images) - 1, sampler=len(gltf.samplers) - 1))
    info = pygltflib.TextureInfo(index=len(gltf.textures) - 1, texCoord=texture.tex_coord)
    if not texture.transform.is_identity():
        t = texture.transform
        info.extensions = {
            TRANSFORM_EXTENSION: {"offset": list(t.offset), "rotation": t.rotation, "scale": list(t.scale)}
        }
        if TRANSFORM_EXTENSION not in gltf.extensionsUsed:
            gltf.extensionsUsed.append(TRANSFORM_EXTENSION)
    return info


def _material(gltf: pygltflib.GLTF2, blob: _Blob, material: PbrMaterial) -> pygltflib.Material:
    pbr = pygltflib.PbrMetallicRoughness(
        baseColorFactor=[float(c) for c in material.base_color_factor],
        metallicFactor=float(material.metallic_factor),
        roughnessFactor=float(material.roughness_factor),
    )
    if material.base_color_texture is not None:
        pbr.baseColorTexture = _texture_info(gltf, blob, material.base_color_texture)
    if material.metallic_roughness_texture is not None:
        pbr.metallicRoughnessTexture = _texture_info(gltf, blob, material.metallic_roughness_texture)
    return pygltflib.Material(
        name=material.name or None, pbrMetallicRoughness=pbr, doubleSided=bool(material.double_sided)
    )


def _check(primitive: Primitive, materials: int) -> None:
    count = len(primitive.positions)
    if primitive.positions.ndim != 2 or primitive.positions.shape[1] != 3 or count == 0:
        raise ConfigError(
            f"primitive '{primitive.name}': positions must be [V, 3] with V > 0, got {primitive.positions.shape}"
        )
    if primitive.indices.ndim != 2 or primitive.indices.shape[1] != 3 or len(primitive.indices) == 0:
        raise ConfigError(
            f"primitive '{primitive.name}': indices must be [F, 3] with F > 0, got {primitive.indices.shape}"
        )
    if primitive.indices.min() < 0 or primitive.indices.max() >= count:
        raise ConfigError(f"primitive '{primitive.name}': an index is outside its {count} vertices")
    for what, values, width in [("normals", primitive.normals, 3)] + [
        (f"uvs[{i}]", uv, 2) for i, uv in enumerate(primitive.uvs)
    ]:
        if values is not None and values.shape != (count, width):
            raise ConfigError(f"primitive '{primitive.name}': {what} must be [{count}, {width}], got {values.shape}")
    if primitive.material is not None and not 0 <= primitive.material < materials:
        raise ConfigError(
            f"primitive '{primitive.name}': material {primitive.material} is not one of the {materials} given"
        )


def write_glb(path, primitives: list[Primitive], materials: list[PbrMaterial], extras: dict | None = None) -> None:
    """Write each primitive as a mesh of its own under a root node (identity transform) to `path` (.glb).

    `extras` (JSON-serialisable) goes to the document's asset.extras."""
    require_pygltflib(pygltflib)
    path = Path(path)
    if not primitives:
        raise ConfigError("write_glb needs at least one primitive")
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="matspray", extras=dict(extras or {})))
    gltf.scene = 0
    gltf.scenes.append(pygltflib.Scene(nodes=list(range(len(primitives)))))
    gltf.buffers.append(pygltflib.Buffer())
    blob = _Blob(gltf)
    gltf.materials = [_material(gltf, blob, material) for material in materials]
    for primitive in primitives:
        _check(primitive, len(materials))
        attributes = pygltflib.Attributes(POSITION=blob.accessor(primitive.positions, pygltflib.VEC3, bounds=True))
        if primitive.normals is not None:
            attributes.NORMAL = blob.accessor(primitive.normals, pygltflib.VEC3)
        for index, uv in enumerate(primitive.uvs):
            setattr(attributes, f"TEXCOORD_{index}", blob.accessor(uv, pygltflib.VEC2))
        mesh = pygltflib.Primitive(
            attributes=attributes,
            indices=blob.accessor(primitive.indices.reshape(-1), pygltflib.SCALAR),
            material=primitive.material,
            mode=pygltflib.TRIANGLES,
        )
        gltf.meshes.append(pygltflib.Mesh(name=primitive.name or None, primitives=[mesh]))
        gltf.nodes.append(pygltflib.Node(name=primitive.name or None, mesh=len(gltf.meshes) - 1))
    blob.data.extend(b"\0" * (-len(blob.data) % 4))
    gltf.buffers[0].byteLength = len(blob.data)
    gltf.set_binary_blob(bytes(blob.data))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    try:
        gltf.save_binary(str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
