"""Files of a synthetic object: ground-truth maps next to each view, relit renders, light maps,
`scene.json`, and the check that an output folder may be written into. Every file is written
atomically (temporary file + rename) by the image and JSON writers used here.

Layout (beside the Blender-layout `transforms_{split}.json` and `{split}/r_000.png` RGBA renders):
    {split}/r_000_basecolor.png        sRGB-encoded, 16 bit RGBA, 0 on background
    {split}/r_000_roughness.png        linear, 16 bit grey + alpha, 0 on background
    {split}/r_000_metallic.png         linear, 16 bit grey + alpha, 0 on background
    {split}/r_000_normal.exr           world-space unit normals (RGB = xyz), 0 on background
    {split}/r_000_depth.exr            camera z along the OpenCV forward axis, 0 on background
    test/r_000_relight_{env}.png       RGBA render under light {env} (straight colour, sRGB)
    envmaps/{env}.exr                  every light used, lat-long, linear, as rendered
    scene.json                         every setting, the seed, and what was made
    object.glb                         a procedural object as glTF 2.0 (meshes, UVs, 8-bit textures)
The alpha channel of the three material maps is the ground-truth coverage (fraction of the
subpixel rays that hit the object); colour values are not premultiplied by it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from matspray.data.formats.blender import read_scene_json
from matspray.data.images import write_image, write_raw
from matspray.errors import SettingError
from matspray.files import write_json
from matspray.synth.groundtruth import GroundTruth

KIND = "matspray-synth"
MAP_BITS = 16
OBJECT_GLB = "object.glb"  # a procedural object's meshes and textures as glTF 2.0 (matspray.synth.gltf_object)
ARTIFACT_PATTERNS = (
    OBJECT_GLB,
    "train/r_*",
    "test/r_*",
    "envmaps/*.exr",
    "transforms_train.json",
    "transforms_test.json",
    "transforms_val.json",
    "scene.json",
)


def tensor(values: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))


def write_ground_truth(folder: Path, name: str, truth: GroundTruth) -> None:
    coverage = tensor(truth.coverage)[..., None]
    write_image(folder / f"{name}_basecolor.png", tensor(truth.base_color), coverage[..., 0], bits=MAP_BITS)
    for what, values in (("roughness", truth.roughness), ("metallic", truth.metallic)):
        write_raw(folder / f"{name}_{what}.png", torch.cat([tensor(values)[..., None], coverage], -1), bits=MAP_BITS)
    write_raw(folder / f"{name}_normal.exr", tensor(truth.normal))
    write_raw(folder / f"{name}_depth.exr", tensor(truth.depth))


def write_render(path: Path, rgb: np.ndarray, alpha: np.ndarray) -> None:
    """RGBA PNG: straight (not premultiplied) colour, sRGB-encoded, alpha from the render."""
    write_image(path, tensor(rgb), tensor(alpha))


def write_envmap(folder: Path, name: str, env: torch.Tensor) -> None:
    write_raw(folder / "envmaps" / f"{name}.exr", env)


# ------------------------------------------------------------------------------------------ scene.json
def prepare_output(out: Path, identity: dict, overwrite: bool) -> None:
    """Refuse to write into a folder holding anything but the same scene, unless `overwrite`; with it,
    remove the previous object's files (only those, nothing else in the folder)."""
    if out.exists() and not out.is_dir():
        raise SettingError("out", f"{out} is a file, not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    previous = read_scene_json(out)
    same = previous is not None and previous.get("kind") == KIND and previous.get("settings") == identity
    if same:
        return
    if not overwrite:
        what = "a different `matspray synth` scene" if previous and previous.get("kind") == KIND else "other files"
        raise SettingError(
            "out", f"{out} already holds {what}; choose another folder or allow overwriting it (overwrite)"
        )
    for pattern in ARTIFACT_PATTERNS:
        for path in sorted(out.glob(pattern)):
            if path.is_file():
                path.unlink()


def write_scene_json(out: Path, record: dict) -> None:
    write_json(out / "scene.json", {"kind": KIND, **record})
