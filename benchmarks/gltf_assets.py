"""Five varied glTF 2.0 benchmark assets, written to a folder for `matspray bench --assets`.

    python -m benchmarks.gltf_assets --out runs/gltf-assets

From the procedural generator (object.glb's writer, matspray.synth.gltf_object.write_object_glb):
  procedural-composite.glb  four parts, one baked material field with metal, dielectric and mixed regions
  procedural-blob-fine.glb  a noisy blob with 512 x 1024 textures (fine texture detail)
By hand (matspray.gltf.write_glb):
  thin-stand.glb            a thin plate, four thin rods and a thin ring; three factor-only materials
  checker-box.glb           a rounded box with a fine checkerboard (KHR_texture_transform, repeat) and a
                            metal / dielectric striped metallic-roughness texture (mirrored repeat)
  vase.gltf                 a vase (sRGB noise-glaze texture), a gold band (factors) and a knob (clamped
                            texture), as .gltf with its buffer and images in external files
Every mesh is closed, since the renderer's BSDFs are one-sided. Prints one line per asset.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pygltflib

from matspray.gltf import PbrMaterial, Primitive, TextureRef, TextureTransform, read_gltf, write_glb
from matspray.gltf.write import encode_base_color, pack_metallic_roughness
from matspray.synth.gltf_object import GLTF_TO_WORLD, write_object_glb
from matspray.synth.materials import bake_textures, random_material
from matspray.synth.noise import ValueNoise, fbm, rotation_about
from matspray.synth.shapes import (
    Part,
    capsule_surface,
    make_part,
    make_shape,
    placed,
    rounded_cube_surface,
    sphere_surface,
    torus_surface,
)

TO_FILE = GLTF_TO_WORLD.T  # our world (+z up) -> glTF's frame (+Y up)


def primitive(part: Part, material: int, name: str | None = None) -> Primitive:
    return Primitive(
        name or part.name, part.vertices @ TO_FILE.T, part.faces, (part.uvs,), part.normals @ TO_FILE.T, material
    )


def procedural(path: Path, shape: str, seed: int, texture_height: int) -> None:
    parts = make_shape(shape, np.random.default_rng([seed, 2]))
    material = random_material(np.random.default_rng([seed, 3]))
    write_object_glb(
        path,
        parts,
        [bake_textures(material, part, texture_height) for part in parts],
        {"source": f"{shape} seed {seed}"},
    )


def box_part(name: str, half: np.ndarray, centre) -> Part:
    """An axis-aligned box: 6 faces of 4 vertices (flat normals, each face the whole UV square)."""
    vertices, faces, uvs, normals = [], [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            a, b = [(axis + 1) % 3, (axis + 2) % 3][:: int(sign)]
            corners = []
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = normal.copy()
                p[a], p[b] = s, t
                corners.append(p * half + centre)
            start = len(vertices)
            vertices += corners
            uvs += [[0, 0], [1, 0], [1, 1], [0, 1]]
            normals += [normal] * 4
            faces += [[start, start + 1, start + 2], [start, start + 2, start + 3]]
    vertices, faces = np.array(vertices), np.array(faces)
    p = vertices[faces]
    assert (
        np.einsum("fi,fi->f", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), np.array(normals)[faces[:, 0]]) > 0
    ).all()
    return Part(name, None, vertices, faces, np.array(uvs, dtype=np.float64), np.array(normals), {})


def thin_stand(path: Path) -> None:
    brass = PbrMaterial("brass", (0.91, 0.67, 0.32, 1.0), 1.0, 0.35)
    plastic = PbrMaterial("red plastic", (0.55, 0.04, 0.05, 1.0), 0.0, 0.75)
    chrome = PbrMaterial("chrome", (0.95, 0.95, 0.96, 1.0), 1.0, 0.08)
    parts = [(box_part("plate", np.array([0.8, 0.55, 0.03]), [0.0, 0.0, -0.6]), 1)]
    for k, (x, y) in enumerate(((-0.6, -0.35), (0.6, -0.35), (-0.6, 0.35), (0.6, 0.35))):
        rod = placed(capsule_surface(0.035, 0.55), np.eye(3), [x, y, -0.02])
        parts.append((make_part(f"rod {k}", rod, {}, 48, 96), 0 if k % 2 == 0 else 2))
    ring = placed(torus_surface(0.62, 0.03), rotation_about([1.0, 0.0, 0.0], np.radians(80.0)), [0.0, 0.0, 0.2])
    parts.append((make_part("ring", ring, {}, 192, 24), 2))
    write_glb(path, [primitive(p, m) for p, m in parts], [brass, plastic, chrome], {"source": "by hand"})


def checker_box(path: Path) -> None:
    size = 256
    y, x = np.mgrid[0:size, 0:size]
    checks = ((x // 8 + y // 8) % 2).astype(np.float64)  # 32 x 32 checks of 8 texels
    colour = np.where(checks[..., None] > 0, [0.85, 0.78, 0.62], [0.10, 0.22, 0.45])
    stripes = (x // 32) % 2  # metal / dielectric stripes, roughness a ramp across them
    roughness = 0.1 + 0.8 * (y / (size - 1))
    mr = pack_metallic_roughness(roughness, stripes.astype(np.float64))
    material = PbrMaterial(
        "checker",
        (1.0, 1.0, 1.0, 1.0),
        1.0,
        1.0,
        TextureRef(encode_base_color(colour), 0, TextureTransform((0.1, 0.05), 0.3, (3.0, 2.0)), "repeat", "repeat"),
        TextureRef(mr, 0, TextureTransform((0.0, 0.0), 0.0, (1.5, 1.5)), "mirror", "mirror"),
    )
    part = make_part("box", rounded_cube_surface(0.7, 6.0), {}, 192, 96)
    write_glb(path, [primitive(part, 0)], [material], {"source": "by hand"})


def vase(path: Path) -> None:
    noise = ValueNoise(np.random.default_rng(21))

    def body(u, v):  # a closed surface of revolution: radius 0 at the top and bottom poles
        radius = np.sin(np.pi * v) * (0.42 + 0.14 * np.sin(2.6 * np.pi * v + 0.4))
        phi = 2.0 * np.pi * u
        return np.stack([radius * np.cos(phi), radius * np.sin(phi), 0.95 - 1.7 * v], axis=-1)

    vase_part = make_part("vase", body, {}, 192, 128)
    height = 256
    u, v = np.meshgrid((np.arange(2 * height) + 0.5) / (2 * height), (np.arange(height) + 0.5) / height)
    glaze = fbm(noise, body(u, v).reshape(-1, 3), 6.0, octaves=4).reshape(height, 2 * height)  # [-1, 1]
    base = np.stack([0.25 + 0.2 * glaze, 0.45 + 0.15 * glaze, 0.35 + 0.1 * glaze], -1).clip(0, 1)
    vase_mr = pack_metallic_roughness((0.25 + 0.2 * np.abs(glaze)).clip(0, 1), np.zeros_like(glaze))
    band = make_part("band", placed(torus_surface(0.5, 0.04), np.eye(3), [0.0, 0.0, 0.25]), {}, 192, 24)
    knob = make_part("knob", placed(sphere_surface(0.12), np.eye(3), [0.0, 0.0, 1.0]), {}, 64, 32)
    knob_mr = pack_metallic_roughness(
        np.tile(np.linspace(0.1, 0.9, 8), (8, 1)), np.tile(np.linspace(0.0, 1.0, 8)[:, None], (1, 8))
    )
    materials = [
        PbrMaterial("glaze", (1.0, 1.0, 1.0, 1.0), 1.0, 1.0, TextureRef(encode_base_color(base)), TextureRef(vase_mr)),
        PbrMaterial("gold", (1.0, 0.78, 0.34, 1.0), 1.0, 0.25),
        PbrMaterial(
            "knob",
            (0.7, 0.7, 0.72, 1.0),
            1.0,
            1.0,
            None,
            TextureRef(knob_mr, 0, TextureTransform((0.2, 0.2), 0.0, (0.6, 0.6)), "clamp", "clamp"),
        ),
    ]
    with tempfile.TemporaryDirectory() as folder:
        glb = Path(folder) / "vase.glb"
        write_glb(
            glb, [primitive(vase_part, 0), primitive(band, 1), primitive(knob, 2)], materials, {"source": "by hand"}
        )
        gltf = pygltflib.GLTF2().load(str(glb))
        with contextlib.redirect_stdout(io.StringIO()):  # pygltflib reports every image it converts
            gltf.convert_images(pygltflib.ImageFormat.FILE, path=str(Path(folder)) + "/")
        gltf.convert_buffers(pygltflib.BufferFormat.BINFILE)
        gltf.save(str(Path(folder) / "vase.gltf"))
        path.parent.mkdir(parents=True, exist_ok=True)
        for file in Path(folder).iterdir():
            if file.name != "vase.glb":
                shutil.copy(file, path.parent / file.name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the assets")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    builders = {
        "procedural-composite.glb": lambda p: procedural(p, "composite", 11, 256),
        "procedural-blob-fine.glb": lambda p: procedural(p, "blob", 12, 512),
        "thin-stand.glb": thin_stand,
        "checker-box.glb": checker_box,
        "vase/vase.gltf": vase,
    }
    for name, build in builders.items():
        build(args.out / name)
        asset = read_gltf(args.out / name)
        textures = sum(
            (m.base_color_texture is not None) + (m.metallic_roughness_texture is not None) for m in asset.materials
        )
        triangles = sum(len(p.indices) for p in asset.primitives)
        print(
            f"{name}: {len(asset.primitives)} primitives, {triangles} triangles, "
            f"{len(asset.materials)} materials, {textures} textures"
        )


if __name__ == "__main__":
    main()
