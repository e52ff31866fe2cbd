"""glTF 2.0 files in and out (metallic-roughness materials), on top of pygltflib's document model.

`read_gltf` turns a .glb/.gltf into plain arrays (`GltfAsset`: triangle primitives placed in the file's
frame, materials with their factors and decoded textures); `write_glb` writes meshes and materials back;
`sample_texture` is the bilinear texture lookup with glTF's wrap modes, shared by renderer and ground truth.

Why pygltflib and not trimesh: pygltflib is a faithful model of the glTF 2.0 schema (every field, its
defaults, extensions as dicts, GLB save), which is what ground truth needs; trimesh turns a file into
its own scene and material classes and drops or bakes what they lack (a texture's texCoord set,
KHR_texture_transform, sampler wrap modes), so its materials would not be the file's.
"""

from matspray.gltf.model import GltfAsset, PbrMaterial, Primitive, TextureRef, TextureTransform
from matspray.gltf.read import read_gltf
from matspray.gltf.sample import sample_texture
from matspray.gltf.write import write_glb

__all__ = [
    "GltfAsset",
    "PbrMaterial",
    "Primitive",
    "TextureRef",
    "TextureTransform",
    "read_gltf",
    "sample_texture",
    "write_glb",
]
