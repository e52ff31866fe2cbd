"""Benchmark objects and glTF 2.0 files, both ways.

`asset_parts`: a glTF asset (matspray.gltf.read_gltf) as the parts and textures that `make_object`
renders and ray casts: every triangle primitive becomes a part, placed in our world (glTF +Y up ->
world +z up, then centred and scaled into the unit sphere, or kept as it is), and its material's
factors are multiplied into its textures (base colour decoded from sRGB; roughness = G, metallic = B
of the metallic-roughness texture), read with the file's UV set, KHR_texture_transform and wrap modes.
`write_object_glb`: the parts and textures of an object back to a .glb in glTF's frame (+Y up), so that
`asset_parts(read_gltf(...), placement="keep")` gives the same object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from matspray.errors import ConfigError, file_error
from matspray.gltf.model import GLTF_TO_WORLD, GltfAsset, PbrMaterial, Primitive, TextureRef, TextureTransform
from matspray.gltf.write import encode_base_color, pack_metallic_roughness, write_glb
from matspray.synth.config import (
    PLACEMENTS,
)  # fit: centre the bounding box, farthest vertex at FIT_RADIUS; keep: as in the file
from matspray.synth.materials import Sampling, Textures, single_wrap, srgb_to_linear
from matspray.synth.shapes import Part, drop_degenerate

FIT_RADIUS = 1.0


def asset_to_world(asset: GltfAsset, placement: str = "fit") -> np.ndarray:  # -> [4, 4] file frame -> world
    if placement not in PLACEMENTS:
        raise ConfigError(f"unknown placement '{placement}' (valid: {', '.join(PLACEMENTS)})")
    matrix = np.eye(4)
    matrix[:3, :3] = GLTF_TO_WORLD
    if placement == "keep":
        return matrix
    points = np.concatenate([p.positions for p in asset.primitives])  # [N, 3]
    centre = 0.5 * (points.min(0) + points.max(0))
    radius = float(np.linalg.norm(points - centre, axis=1).max())
    if not radius > 0.0:
        raise file_error(asset.path, "all vertices lie at one point", "the asset has no extent to render")
    scale = FIT_RADIUS / radius
    matrix[:3, :3] *= scale
    matrix[:3, 3] = -scale * GLTF_TO_WORLD @ centre
    return matrix


def texture_sampling(texture: TextureRef) -> Sampling:
    to_uv = None if texture.transform.is_identity() else texture.transform.matrix()
    return Sampling(to_uv, texture.wrap_s, texture.wrap_t)


def material_textures(material: PbrMaterial) -> Textures:
    """The material's linear maps with its factors multiplied in (1 x 1 maps where it has no texture)."""
    factor = np.asarray(material.base_color_factor[:3], dtype=np.float64)
    base, base_sampling = np.broadcast_to(factor, (1, 1, 3)), Sampling()
    if material.base_color_texture is not None:
        image = material.base_color_texture.image
        rgb = image[..., :3] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=2)  # grey (+ alpha) images
        base, base_sampling = (
            srgb_to_linear(rgb.astype(np.float64)) * factor,
            texture_sampling(material.base_color_texture),
        )
    rough = np.full((1, 1), material.roughness_factor, dtype=np.float64)
    metal = np.full((1, 1), material.metallic_factor, dtype=np.float64)
    mr_sampling = Sampling()
    if material.metallic_roughness_texture is not None:
        image = material.metallic_roughness_texture.image
        green, blue = (image[..., 1], image[..., 2]) if image.shape[2] >= 3 else (image[..., 0], image[..., 0])
        rough, metal = green * material.roughness_factor, blue * material.metallic_factor
        mr_sampling = texture_sampling(material.metallic_roughness_texture)
    as_map = lambda values: np.ascontiguousarray(np.clip(values, 0.0, 1.0), dtype=np.float32)  # noqa: E731
    return Textures(as_map(base), as_map(rough), as_map(metal), base_sampling, mr_sampling, material.double_sided)


def primitive_uvs(asset: GltfAsset, primitive: Primitive, material: PbrMaterial) -> np.ndarray:  # -> [V, 2]
    sets = {t.tex_coord for t in (material.base_color_texture, material.metallic_roughness_texture) if t is not None}
    if not sets:
        return np.zeros((len(primitive.positions), 2))
    if len(sets) > 1:
        raise file_error(
            asset.path,
            f"mesh '{primitive.name}': its base colour and metallic-roughness textures use two UV sets "
            f"({sorted(sets)})",
            "re-export the asset with one UV set per material",
        )
    index = sets.pop()
    if index >= len(primitive.uvs):
        raise file_error(
            asset.path, f"mesh '{primitive.name}': its material reads TEXCOORD_{index}, which the mesh does not have"
        )
    uvs = primitive.uvs[index]
    if not np.isfinite(uvs).all():
        raise file_error(asset.path, f"mesh '{primitive.name}': a texture coordinate is not finite")
    for texture in (material.base_color_texture, material.metallic_roughness_texture):
        if texture is not None and len(
            uvs
        ):  # texel indices must stay exact integers (KHR_texture_transform can scale by 1e300)
            matrix = texture.transform.matrix()
            reach = float(np.abs(uvs @ matrix[:2, :2].T + matrix[:2, 2]).max()) * max(texture.image.shape[:2])
            if not reach < 2.0**52:
                raise file_error(
                    asset.path,
                    f"mesh '{primitive.name}': its texture coordinates, with the texture's KHR_texture_transform, "
                    f"reach texel {reach:.3g}",
                    "fix the texture transform or the UVs",
                )
    return uvs


def flat_shaded(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Vertices split per face with the face's normal (glTF's rule for meshes without normals)."""
    corners = faces.reshape(-1)
    p = vertices[faces]  # [F, 3, 3]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True).clip(1e-30)
    return vertices[corners], np.arange(len(corners)).reshape(-1, 3), uvs[corners], np.repeat(normal, 3, axis=0)


def asset_parts(asset: GltfAsset, placement: str = "fit") -> tuple[list[Part], list[Textures], np.ndarray]:
    """One part per triangle primitive, its textures, and the 4 x 4 asset_to_world used."""
    matrix = asset_to_world(asset, placement)
    linear, offset = matrix[:3, :3], matrix[:3, 3]
    parts, textures = [], []
    for index, primitive in enumerate(asset.primitives):
        material = asset.material_of(primitive)
        uvs = primitive_uvs(asset, primitive, material)
        vertices = primitive.positions @ linear.T + offset
        faces = drop_degenerate(vertices, primitive.indices)
        if len(faces) == 0:
            continue
        if primitive.normals is None:
            vertices, faces, uvs, normals = flat_shaded(vertices, faces, uvs)
        else:
            normals = primitive.normals @ GLTF_TO_WORLD.T
        params = {
            "primitive": primitive.name,
            "material": material.name
            or (f"material {primitive.material}" if primitive.material is not None else "default"),
        }
        parts.append(Part(f"asset/{index}", None, vertices, faces, uvs, normals, params))
        textures.append(material_textures(material))
        for values, sampling in (
            (textures[-1].base_color, textures[-1].base_color_sampling),
            (textures[-1].roughness, textures[-1].metallic_roughness_sampling),
        ):
            try:  # what the renderer will do with two wrap modes, checked before anything is written
                single_wrap(values, sampling, uvs)
            except ConfigError as error:
                raise file_error(asset.path, f"mesh '{primitive.name}': {error}") from None
    if not parts:
        raise file_error(
            asset.path, "every triangle of the default scene has zero area", "the asset has no surface to render"
        )
    return parts, textures, matrix


def write_object_glb(path: Path, parts: list[Part], textures: list[Textures], extras: dict | None = None) -> None:
    """The object as a .glb in glTF's frame: one primitive and one material per part, textures as 8-bit PNGs
    (base colour sRGB-encoded, roughness in G and metallic in B), factors 1."""
    primitives, materials = [], []
    for index, (part, texture) in enumerate(zip(parts, textures)):
        to_file = GLTF_TO_WORLD.T  # the inverse rotation
        primitives.append(
            Primitive(part.name, part.vertices @ to_file.T, part.faces, (part.uvs,), part.normals @ to_file.T, index)
        )
        materials.append(
            PbrMaterial(
                name=part.name,
                base_color_factor=(1.0, 1.0, 1.0, 1.0),
                metallic_factor=1.0,
                roughness_factor=1.0,
                base_color_texture=TextureRef(
                    encode_base_color(texture.base_color),
                    0,
                    file_transform(texture.base_color_sampling),
                    texture.base_color_sampling.wrap_s,
                    texture.base_color_sampling.wrap_t,
                ),
                metallic_roughness_texture=TextureRef(
                    pack_metallic_roughness(texture.roughness, texture.metallic),
                    0,
                    file_transform(texture.metallic_roughness_sampling),
                    texture.metallic_roughness_sampling.wrap_s,
                    texture.metallic_roughness_sampling.wrap_t,
                ),
            )
        )
    write_glb(path, primitives, materials, extras)


def file_transform(sampling: Sampling) -> TextureTransform:
    if sampling.to_uv is None:
        return TextureTransform()
    raise ConfigError("only untransformed textures are written back to glTF")
