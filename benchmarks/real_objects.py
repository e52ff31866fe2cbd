"""The real-object benchmark sets `real-dev` and `real-eval`: eight artist-made glTF objects with textured
metallic-roughness materials, the one place that names them, where they came from, and how they are split.

Each object is kept in the repository as `benchmarks/real/SPLIT/NAME.glb` (textures of at most 512 px), made from
its source file by `python -m benchmarks.convert_real` (which checks the source's SHA-256 and writes the split's
folder); THIRD_PARTY_NOTICES.md records each one's title, author, source, licence and the changes made.

The split, fixed before any object was run: the objects are grouped by kind ("metal": at least 15 % of the surface
has metallic > 0.5, measured on the converted file; "dielectric": the rest), each group sorted by name and shuffled
by numpy's default_rng(80); `real-dev` takes the first two metal objects and the first dielectric one,
`real-eval` the other five (two metal, three dielectric). The evaluation objects are run once, on final defaults.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matspray.errors import ConfigError, file_error

REPO_ROOT = Path(__file__).resolve().parents[1]
REAL_DIR = REPO_ROOT / "benchmarks" / "real"
SPLIT_SEED = 80
DEV_PICKS = {"metal": 2, "dielectric": 1}  # how many of each kind the development set takes
METAL_AREA = 0.15  # an object is "metal" when at least this share of its surface has metallic > 0.5
KHRONOS = "DRx3D/glTF-Sample-Assets-OLD"  # the copy of KhronosGroup/glTF-Sample-Assets the files were taken from
KHRONOS_COMMIT = "02d48689ce60c8799207f180ae324997e974c956"
CC0, CC_BY = "CC0-1.0", "CC-BY-4.0"


@dataclass(frozen=True)
class RealObject:
    name: str  # the file's stem
    title: str
    author: str
    licence: str  # SPDX identifier of the model's files
    repo: str  # GitHub owner/name the source was taken from
    commit: str
    path: str  # the source .gltf/.glb in that repository
    source_sha256: str  # of the source file and every file it refers to (`convert_real.source_digest`)
    kind: str  # "metal" or "dielectric" (METAL_AREA; a test measures it on the committed file)
    drop_materials: tuple[str, ...] = ()  # primitives with these materials are left out
    note: str = ""  # what else the conversion leaves behind


OBJECTS = (
    RealObject(
        "avocado",
        "Avocado",
        "Microsoft",
        CC0,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/Avocado/glTF/Avocado.gltf",
        "63a53e1205986eb7d7f49d56c816fc614fa32e384930b9b68e4f150e09c9e07a",
        "dielectric",
    ),
    RealObject(
        "barrel",
        "Barrel",
        "Shannon Poole",
        CC_BY,
        "webgltf/webgltf-sample-models",
        "b7c45810b571ea2c43bfbb544e1d2e08e882d157",
        "models/Barrel/glTF-Binary/barrel.glb",
        "e186cc17efafaf1b5a7d941346c04c8e668c5cfc387f10f4e28882b641ff053d",
        "metal",
    ),
    RealObject(
        "boom-box",
        "Boom Box (from Boom Box with Axes)",
        "Microsoft",
        CC0,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/BoomBoxWithAxes/glTF/BoomBoxWithAxes.gltf",
        "6c4f34f4f423e56fdb6e7bb1537fa8e95c1404a796845f0c670b5d8984598938",
        "dielectric",
        drop_materials=("M_Coordinates",),
        note="the three axis arrows left out",
    ),
    RealObject(
        "iridescence-lamp",
        "Iridescence Lamp",
        "Eric Chadwick, Wayfair LLC",
        CC_BY,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/IridescenceLamp/glTF/IridescenceLamp.gltf",
        "a5e89e2be688205849aff01761f1a2f8733d38175bcc236731958ac54d297c8b",
        "metal",
        note="transmission, volume and iridescence left out: the glass cover is opaque",
    ),
    RealObject(
        "sheen-chair",
        "SheenChair",
        "Eric Chadwick, Wayfair LLC",
        CC_BY,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/SheenChair/glTF/SheenChair.gltf",
        "539e583246cd8706631aae2038f878f5da5e17a9899d3267b7fbd90bd09c4455",
        "dielectric",
        note="the default variant (Mango Velvet); sheen and the other variant left out",
    ),
    RealObject(
        "tea-set",
        "Tea Set 01 (Poly Haven), posed",
        "Poly Haven (model); Toyota Research Institute (posing)",
        CC0,
        "RobotLocomotion/models",
        "4723170e1c8ee8bc59c342bb5c491ab8f263f1fb",
        "tutorials/models/assets/tea_set_posed.gltf",
        "5864cc408ccf31988a81d461b40961b1dff7e39fa090611d0e5264c24eac3048",
        "dielectric",
    ),
    RealObject(
        "toy-car",
        "Toy Car",
        "Guido Odendahl (model), Eric Chadwick (materials)",
        CC0,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/ToyCar/glTF/ToyCar.gltf",
        "203969b55a9500b1d6145f69bbac9de9d9c24cf2270d8dc4288b3c80a9f0844f",
        "metal",
        drop_materials=("Fabric",),
        note="the cloth under the car left out; clearcoat and transmission left out: the windscreen is opaque",
    ),
    RealObject(
        "water-bottle",
        "Water Bottle",
        "Microsoft",
        CC0,
        KHRONOS,
        KHRONOS_COMMIT,
        "Models/WaterBottle/glTF/WaterBottle.gltf",
        "a8a3a1289768b3900227cd4eb84225b76db803e8a4c43d58d0f846719c3bbb14",
        "metal",
    ),
)
SETS = ("real-dev", "real-eval")


def split(objects=OBJECTS) -> dict[str, tuple[RealObject, ...]]:
    """{"real-dev": ..., "real-eval": ...} by the rule of the module's docstring (each set sorted by name)."""
    rng = np.random.default_rng(SPLIT_SEED)
    dev, evaluation = [], []
    for kind in sorted(DEV_PICKS):
        group = sorted((o for o in objects if o.kind == kind), key=lambda o: o.name)
        shuffled = [group[int(i)] for i in rng.permutation(len(group))]
        dev += shuffled[: DEV_PICKS[kind]]
        evaluation += shuffled[DEV_PICKS[kind] :]
    by_name = lambda chosen: tuple(sorted(chosen, key=lambda o: o.name))  # noqa: E731
    return {"real-dev": by_name(dev), "real-eval": by_name(evaluation)}


def set_folder(which: str) -> Path:
    """Where the set's .glb files are kept: `matspray bench --assets` takes this folder."""
    if which not in SETS:
        raise ConfigError(f"unknown real object set '{which}'; choose one of {', '.join(SETS)}")
    return REAL_DIR / which.removeprefix("real-")


def set_files(which: str) -> list[Path]:
    """The set's committed .glb files, in the split's order (by name)."""
    folder = set_folder(which)
    files = [folder / f"{o.name}.glb" for o in split()[which]]
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise file_error(
            folder,
            f"the real object set '{which}' lacks {', '.join(missing)}",
            "run `python -m benchmarks.convert_real --sources DIR`, see benchmarks/real_objects.py",
        )
    return files


def metal_share(path) -> float:
    """The share of the object's surface area whose metallic (texture times factor, as the renderer reads it at
    each triangle's centre) is above 0.5."""
    from matspray.gltf import read_gltf
    from matspray.synth.gltf_object import asset_parts

    parts, textures, _ = asset_parts(read_gltf(path))
    return parts_metal_share(parts, textures)


def parts_metal_share(parts, textures) -> float:
    """`metal_share` of an object already read (`asset_parts`: its parts and their textures)."""
    from matspray.synth.materials import texture_lookup

    metal = total = 0.0
    for part, texture in zip(parts, textures):
        corners = part.vertices[part.faces]  # [F, 3, 3]
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=-1)
        centre_uv = part.uvs[part.faces].mean(axis=1)  # [F, 2]
        metallic = texture_lookup(texture.metallic, centre_uv, texture.metallic_roughness_sampling)
        metal += float(area[metallic > 0.5].sum())
        total += float(area.sum())
    return metal / total
