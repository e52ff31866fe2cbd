"""The real benchmark objects (benchmarks/real_objects.py) made from their source files, reproducibly.

    python -m benchmarks.convert_real --sources DIR [--out benchmarks/real] [--only NAME ...]

DIR holds each source repository as DIR/OWNER/NAME/ (a checkout, or the object's files copied at the commit
that real_objects.py names, in their folders). Each object's source is checked against its SHA-256 (the file and
every file it refers to), read by matspray's glTF reader (every triangle primitive of the default scene, placed by
its nodes) and written back by `write_glb` as plain glTF: the primitives of `drop_materials` left out, only the
materials still used, their factors, UV sets, KHR_texture_transform and wrap modes kept; textures box-filtered to
at most MAX_SIDE px; the base colour as RGB (alpha dropped), the metallic-roughness texture as G roughness and B
metallic (R, where some sources keep occlusion, set to 0). What the renderer does not read is left out: normal,
occlusion and emissive textures, emissive factors, alpha modes and material extensions (sheen, clearcoat,
transmission, iridescence, variants). Writes OUT/SPLIT/NAME.glb and prints one line per object.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from dataclasses import replace
from pathlib import Path
from urllib.parse import unquote

import numpy as np
from PIL import Image

from benchmarks.real_objects import OBJECTS, REAL_DIR, RealObject, metal_share, split
from matspray.errors import MatsprayError, file_error
from matspray.gltf import PbrMaterial, TextureRef, read_gltf, write_glb
from matspray.gltf.document import load_document

MAX_SIDE = 512


def source_digest(path: Path) -> str:
    """SHA-256 over the file and every external file it refers to (buffers, images), each as 'name digest'."""
    gltf, _ = load_document(path)
    uris = [item.uri for item in (*gltf.buffers, *gltf.images) if item.uri and not item.uri.startswith("data:")]
    lines = [f"{path.name} {hashlib.sha256(path.read_bytes()).hexdigest()}"]
    for uri in sorted(set(uris)):
        lines.append(f"{uri} {hashlib.sha256((path.parent / unquote(uri)).read_bytes()).hexdigest()}")
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def shrink(image: np.ndarray) -> np.ndarray:  # [H, W, C] in [0, 1] -> [h, w, C], max(h, w) <= MAX_SIDE
    """Box-filtered (each texel the mean of those it covers: no ringing across metal / dielectric edges)."""
    height, width = image.shape[:2]
    if max(height, width) <= MAX_SIDE:
        return image
    scale = MAX_SIDE / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    channels = [  # in float ("F"): PIL's 8-bit box filter rounds its sums off by up to one level
        np.asarray(Image.fromarray(image[..., c].astype(np.float32), mode="F").resize(size, Image.BOX))
        for c in range(image.shape[2])
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def plain_texture(texture: TextureRef | None, metallic_roughness: bool) -> TextureRef | None:
    if texture is None:
        return None
    image = texture.image
    if metallic_roughness:  # -> [0, G, B]; a grey image stands for both, as the reader takes it
        green, blue = (image[..., 1], image[..., 2]) if image.shape[2] >= 3 else (image[..., 0], image[..., 0])
        image = np.stack([np.zeros_like(green), green, blue], axis=-1)
    else:
        image = image[..., :3] if image.shape[2] >= 3 else image[..., :1]  # alpha dropped
    return replace(texture, image=shrink(image))


def plain_material(material: PbrMaterial) -> PbrMaterial:
    return replace(
        material,
        base_color_factor=(*material.base_color_factor[:3], 1.0),
        base_color_texture=plain_texture(material.base_color_texture, metallic_roughness=False),
        metallic_roughness_texture=plain_texture(material.metallic_roughness_texture, metallic_roughness=True),
    )


def convert(spec: RealObject, source: Path, out: Path) -> dict:
    """Write `spec`'s plain .glb to `out` from `source`; returns what was written (for the printed line)."""
    digest = source_digest(source)
    if digest != spec.source_sha256:
        raise file_error(
            source,
            f"SHA-256 {digest} is not the {spec.source_sha256} that benchmarks/real_objects.py records for {spec.name}",
            f"take the files of {spec.repo} at commit {spec.commit}",
        )
    asset = read_gltf(source)
    kept = [p for p in asset.primitives if asset.material_of(p).name not in spec.drop_materials]
    used = sorted({p.material for p in kept if p.material is not None})
    index = {old: new for new, old in enumerate(used)}
    primitives = [replace(p, material=None if p.material is None else index[p.material]) for p in kept]
    materials = [plain_material(asset.materials[old]) for old in used]
    extras = {
        "title": spec.title,
        "author": spec.author,
        "licence": spec.licence,
        "source": f"https://github.com/{spec.repo}/blob/{spec.commit}/{spec.path}",
        "changes": "converted by benchmarks/convert_real.py" + (f"; {spec.note}" if spec.note else ""),
    }
    write_glb(out, primitives, materials, extras)
    textures = [t for m in materials for t in (m.base_color_texture, m.metallic_roughness_texture) if t is not None]
    return {
        "bytes": out.stat().st_size,
        "primitives": len(primitives),
        "triangles": sum(len(p.indices) for p in primitives),
        "textures": sorted({f"{t.image.shape[1]}x{t.image.shape[0]}" for t in textures}),
        "metal": metal_share(out),
        "ignored": asset.notes,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.convert_real",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--sources", type=Path, required=True, help="folder of the source repositories, DIR/OWNER/NAME")
    parser.add_argument("--out", type=Path, default=REAL_DIR, help=f"folder of the sets (default {REAL_DIR})")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME", help="convert only these objects")
    args = parser.parse_args(argv)
    names = {o.name for o in OBJECTS}
    unknown = sorted(set(args.only or ()) - names)
    if unknown:
        parser.error(f"--only: unknown object {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    total = 0
    try:
        for which, objects in split().items():
            for spec in objects:
                if args.only and spec.name not in args.only:
                    continue
                out = args.out / which.removeprefix("real-") / f"{spec.name}.glb"
                done = convert(spec, args.sources / spec.repo / spec.path, out)
                total += done["bytes"]
                print(f"{which} {spec.name}: " + json.dumps(done), flush=True)
    except MatsprayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"written: {total / 2**20:.2f} MiB in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
