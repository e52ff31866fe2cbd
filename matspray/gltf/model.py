"""Plain data of a glTF asset as `read_gltf` returns it and `write_glb` takes it (no pygltflib types)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from matspray.errors import ConfigError

# glTF's frame (+Y up, +Z front) -> ours (+z up): x stays, glTF +Y becomes +z, glTF +Z becomes -y
GLTF_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# glTF sampler wrap enums and our names for them (the names Mitsuba's bitmap texture uses)
WRAP_MODES = {10497: "repeat", 33071: "clamp", 33648: "mirror"}
WRAP_ENUMS = {name: enum for enum, name in WRAP_MODES.items()}


def require_pygltflib(module) -> None:
    """ConfigError saying what to install when the optional pygltflib (`module`, None when missing) is absent."""
    if module is None:
        raise ConfigError("reading and writing glTF needs pygltflib: pip install 'matspray[gltf]'")


@dataclass(frozen=True)
class TextureTransform:
    """KHR_texture_transform: uv' = T(offset) R(rotation) S(scale) uv."""

    offset: tuple[float, float] = (0.0, 0.0)
    rotation: float = 0.0  # radians, counter-clockwise in UV space as the extension defines it
    scale: tuple[float, float] = (1.0, 1.0)

    def matrix(self) -> np.ndarray:  # [3, 3] affine map of homogeneous (u, v, 1)
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        translation = np.array([[1.0, 0.0, self.offset[0]], [0.0, 1.0, self.offset[1]], [0.0, 0.0, 1.0]])
        rotation = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        scale = np.diag([self.scale[0], self.scale[1], 1.0])
        return translation @ rotation @ scale

    def is_identity(self) -> bool:
        return np.allclose(self.matrix(), np.eye(3), atol=0.0)


@dataclass(frozen=True)
class TextureRef:
    """A texture as a material uses it. `image` holds the stored values in [0, 1] (a base colour texture
    stays sRGB-encoded here); row 0 is the image's top row, at v = 0 (glTF's UV origin)."""

    image: np.ndarray  # [H, W, C] float32, C in 1..4
    tex_coord: int = 0  # TEXCOORD_n set (KHR_texture_transform's texCoord override applied)
    transform: TextureTransform = field(default_factory=TextureTransform)
    wrap_s: str = "repeat"  # one of WRAP_MODES' names, along u
    wrap_t: str = "repeat"  # along v
    source: str = ""  # where the image came from (file name or 'image 3'), for messages


@dataclass(frozen=True)
class PbrMaterial:
    """pbrMetallicRoughness; the defaults are glTF's default material."""

    name: str = ""
    base_color_factor: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)  # linear RGBA
    metallic_factor: float = 1.0
    roughness_factor: float = 1.0
    base_color_texture: TextureRef | None = None  # sRGB-encoded RGB(A)
    metallic_roughness_texture: TextureRef | None = None  # linear: G = roughness, B = metallic
    double_sided: bool = False  # glTF doubleSided: back faces are shaded too (with the normal turned round)


@dataclass(frozen=True)
class Primitive:
    """One triangle primitive, placed by its node's world transform in the file's own frame."""

    name: str
    positions: np.ndarray  # [V, 3] float64
    indices: np.ndarray  # [F, 3] int64, counter-clockwise seen from the front
    uvs: tuple[np.ndarray, ...] = ()  # TEXCOORD_0, TEXCOORD_1, ...: [V, 2] float64 each
    normals: np.ndarray | None = None  # [V, 3] float64 unit, or None (the file has none)
    material: int | None = None  # index into GltfAsset.materials; None: glTF's default material


@dataclass(frozen=True)
class GltfAsset:
    path: str
    primitives: list[Primitive]
    materials: list[PbrMaterial]
    notes: list[str]  # what was skipped or ignored, one line each
    extras: dict  # the document's asset.extras (dict only)

    def material_of(self, primitive: Primitive) -> PbrMaterial:
        return PbrMaterial() if primitive.material is None else self.materials[primitive.material]
