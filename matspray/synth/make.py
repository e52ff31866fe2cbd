"""`make_object`: one synthetic benchmark object, from settings to a complete folder."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from matspray import __version__
from matspray.data.formats.blender import write_blender
from matspray.data.scene import View
from matspray.errors import ConfigError, SettingError
from matspray.gltf.read import read_gltf
from matspray.render.shade.lights import default_relight_names, load_envmap
from matspray.synth.cameras import FOV_X, GROUND_MIN_ELEVATION, MIN_ELEVATION, make_cameras
from matspray.synth.config import SynthConfig
from matspray.synth.gltf_object import asset_parts, write_object_glb
from matspray.synth.groundtruth import cast_ground_truth
from matspray.synth.materials import Textures, bake_textures, random_material, table_texture, toned
from matspray.synth.mitsuba_scene import (
    GROUND_BASE_COLOR,
    GROUND_ROUGHNESS,
    MAX_DEPTH,
    GroundPlane,
    build_scene,
    render_view,
    sampler_for,
    select_variant,
)
from matspray.synth.shapes import Part, make_shape, resolve_shape
from matspray.synth.writer import (
    OBJECT_GLB,
    prepare_output,
    write_envmap,
    write_ground_truth,
    write_render,
    write_scene_json,
)

# independent random streams of one seed
SHAPE_STREAM, MATERIAL_STREAM, CAMERA_STREAM = 2, 3, 4


@dataclass
class SynthResult:
    out: Path
    variant: str  # Mitsuba variant that rendered it
    shape: str
    train_env: str
    relight_envs: list[str]
    seconds: float


def render_seed(seed: int, light: int, split: int, view: int) -> int:
    """Mitsuba sampler seed of one render (distinct per light, split and view; fits in 31 bits)."""
    return int(np.random.default_rng([seed, 5, light, split, view]).integers(0, 2**31 - 1))


def resolve_lights(config: SynthConfig) -> tuple[str, list[str], dict[str, torch.Tensor]]:
    """Training light name, relight names and every map by name, loaded at the working size."""
    train_name, train_map = load_envmap(config.env, config.env_height)
    specs = config.relight_envs if config.relight_envs is not None else default_relight_names(train_name)
    maps = {train_name: train_map}
    relight_names = []
    for spec in specs:
        name, env = load_envmap(spec, config.env_height)
        if name in maps and not torch.equal(maps[name], env):
            raise ConfigError(
                f"two different lights are both called '{name}' ({spec!r} and another); rename one of the files"
            )
        if name in relight_names:
            raise SettingError("relight_envs", f"names the light '{name}' twice")
        maps[name] = env
        relight_names.append(name)
    return train_name, relight_names, maps


@dataclass
class ObjectContent:
    """What is rendered: the parts, their textures, and how scene.json describes them."""

    shape: str  # a procedural shape's name, or 'asset'
    parts: list[Part]
    textures: list[Textures]
    description: dict  # scene.json entries: shape, parts, material or asset


def procedural_content(config: SynthConfig) -> ObjectContent:
    shape = resolve_shape(config.shape, config.seed)
    parts = make_shape(shape, np.random.default_rng([config.seed, SHAPE_STREAM]))
    material = random_material(np.random.default_rng([config.seed, MATERIAL_STREAM]))
    textures = [bake_textures(material, part, config.texture_height) for part in parts]
    if config.tabletop != "grey":
        textures = [toned(t, config.tabletop) for t in textures]
    description = {
        "shape": shape,
        "parts": [{"name": p.name, **p.params} for p in parts],
        "material": material.to_json(),
    }
    return ObjectContent(shape, parts, textures, description)


def asset_content(config: SynthConfig, notify: Callable[[str], None]) -> ObjectContent:
    """A glTF asset's parts and textures (matspray.synth.gltf_object); what it ignores is said once."""
    asset = read_gltf(config.asset)
    if asset.notes:
        notify(f"{config.asset}: ignored: {'; '.join(asset.notes)}")
    parts, textures, matrix = asset_parts(asset, config.placement)
    description = {
        "shape": "asset",
        "parts": [{"name": p.name, **p.params} for p in parts],
        "asset": {
            "file": str(config.asset),
            "sha256": hashlib.sha256(Path(config.asset).read_bytes()).hexdigest(),
            "placement": config.placement,
            "asset_to_world": matrix.tolist(),
            "ignored": asset.notes,
            "up": "glTF +Y -> world +z",
        },
    }
    return ObjectContent("asset", parts, textures, description)


def make_object(config: SynthConfig, out, progress: bool = True, notify: Callable[[str], None] = print) -> SynthResult:
    """Render a synthetic object (procedural, or `config.asset`'s glTF file) with its ground truth into
    folder `out` (see matspray.synth.writer). Everything is read and checked before anything is written."""
    start = time.perf_counter()
    out = Path(out)
    config.validate()
    content = procedural_content(config) if config.asset is None else asset_content(config, notify)
    parts, textures, shape = content.parts, content.textures, content.shape
    train_env, relight_envs, lights = resolve_lights(config)
    identity = config.identity()
    if config.asset is not None:
        identity["asset_sha256"] = content.description["asset"]["sha256"]
    prepare_output(out, identity, config.overwrite)
    variant = select_variant()
    notify(f"Mitsuba variant: {variant}")

    bounding_radius = float(max(np.linalg.norm(p.vertices, axis=1).max() for p in parts))
    train_cameras, test_cameras, distance = make_cameras(
        config.train_views,
        config.test_views,
        bounding_radius,
        config.resolution,
        np.random.default_rng([config.seed, CAMERA_STREAM]),
        GROUND_MIN_ELEVATION if config.ground else MIN_ELEVATION,
        config.cameras,
        config.fill,
    )
    ground = None
    if config.ground:  # touching the object's lowest point, wide enough to fill the lower background
        table = None if config.tabletop == "grey" else table_texture(config.tabletop, config.seed)
        ground = GroundPlane(float(min(p.vertices[:, 2].min() for p in parts)), 4.0 * distance, table)
    record = scene_record(
        config, identity, variant, content.description, train_env, relight_envs, distance, bounding_radius, ground
    )
    out.mkdir(parents=True, exist_ok=True)
    write_scene_json(out, record)
    for name, env in lights.items():
        write_envmap(out, name, env)
    if config.asset is None:
        write_object_glb(
            out / OBJECT_GLB,
            parts,
            textures,
            {"matspray": {"kind": "matspray-synth object", "shape": shape, "seed": config.seed}},
        )

    splits = {"train": train_cameras, "test": test_cameras}
    total = len(train_cameras) + len(test_cameras) * (2 + len(relight_envs)) + len(train_cameras)
    bar = tqdm(total=total, desc="synth", unit="render", disable=not progress)
    views: dict[str, list[View]] = {"train": [], "test": []}
    scene = build_scene(parts, textures, lights[train_env].numpy())  # the object alone: its ground truth
    photo_scene = (
        build_scene(parts, textures, lights[train_env].numpy(), config.background == "env", ground)
        if config.unmasked
        else scene
    )
    for split_index, (split, cameras) in enumerate(splits.items()):
        for index, camera in enumerate(cameras):
            name = f"r_{index:03d}"
            rgb, alpha = render_view(photo_scene, camera, config.spp, render_seed(config.seed, 0, split_index, index))
            mask = None if config.unmasked else torch.from_numpy(alpha)  # an unmasked photo is RGB only
            views[split].append(View(name, torch.from_numpy(rgb), mask, camera))
            bar.update()
            write_ground_truth(out / split, name, cast_ground_truth(scene, textures, camera, config.gt_samples))
            bar.update()
    write_blender(out, views)
    for light_index, env_name in enumerate(relight_envs, start=1):
        scene = build_scene(parts, textures, lights[env_name].numpy())
        for index, camera in enumerate(test_cameras):
            rgb, alpha = render_view(scene, camera, config.spp, render_seed(config.seed, light_index, 1, index))
            write_render(out / "test" / f"r_{index:03d}_relight_{env_name}.png", rgb, alpha)
            bar.update()
    bar.close()
    record["status"] = "complete"
    write_scene_json(out, record)
    return SynthResult(out, variant, shape, train_env, relight_envs, time.perf_counter() - start)


def scene_record(
    config: SynthConfig,
    identity: dict,
    variant: str,
    description: dict,
    train_env: str,
    relight_envs: list,
    distance: float,
    bounding_radius: float,
    ground,
) -> dict:
    """scene.json's record of an object being made: its settings, content, lights, cameras, how it was rendered and
    what its ground truth holds ("incomplete" until every file is written)."""
    return {
        "matspray_version": __version__,
        "settings": identity,
        "seed": config.seed,
        "variant": variant,
        **description,
        "lights": {"train": train_env, "relight": relight_envs},
        "cameras": {
            "fov_x": FOV_X,
            "layout": config.cameras,
            "distance": distance,
            "bounding_radius": bounding_radius,
            "up": [0, 0, 1],
            "train": config.train_views,
            "test": config.test_views,
        },
        "render": {
            "renderer": "mitsuba",
            "integrator": "path",
            "max_depth": MAX_DEPTH,
            "spp": config.spp,
            "sampler": sampler_for(config.spp),
            "bsdf": "principled (specular 0.5, no sheen/clearcoat/transmission)",
            "film_filter": "box",
            "rgba": "straight (not premultiplied) sRGB-encoded colour, alpha from the render",
        },
        "ground_truth": {
            "subpixel_samples": config.gt_samples**2,
            "alpha_channel": "coverage (PNG maps)",
            "background": 0,
            "basecolor": "sRGB-encoded 16-bit PNG",
            "roughness": "linear 16-bit PNG (GGX alpha = r^2)",
            "metallic": "linear 16-bit PNG",
            "normal": "EXR world-space unit xyz",
            "depth": "EXR camera z (OpenCV forward), 0 on background",
        },
        "photos": {
            "background": config.background,
            "masks": "none (true masks: the ground truth's alpha)" if config.unmasked else "alpha channel",
            "ground": None
            if ground is None
            else {
                "z": ground.z,
                "half_size": ground.half_size,
                "base_color": GROUND_BASE_COLOR if ground.texture is None else f"a {config.tabletop} table's texture",
                "roughness": GROUND_ROUGHNESS,
                "metallic": 0.0,
            },
            "relit": "the object alone (no ground, light hidden), alpha = coverage",
        },
        "status": "incomplete",
    }
