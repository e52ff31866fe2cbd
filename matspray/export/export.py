"""The whole export: asset -> closed surface -> decimated mesh -> UV atlas -> baked textures -> GLB
(one metallic-roughness material) + the estimated environment map beside it as .exr and .hdr."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.data.images import atomic_target, read_image, write_image
from matspray.data.loader import load_run_scene
from matspray.errors import ConfigError, RunError
from matspray.export.atlas import uv_atlas
from matspray.export.bake import ViewBake, bake_textures, blend_normals, gaussian_weights
from matspray.export.config import ExportConfig
from matspray.export.contour import FIT_VIEWS, fit_silhouettes
from matspray.export.decimate import decimate
from matspray.export.frames import file_from_dataset, frame_extras, transform_directions, transform_points
from matspray.export.normals import smoothed_vertex_normals, unit_normals
from matspray.export.silhouette import spread
from matspray.export.surface import fuse_surface
from matspray.files import check_output_file
from matspray.gltf.model import PbrMaterial, Primitive, TextureRef
from matspray.gltf.write import encode_base_color, pack_metallic_roughness, write_glb
from matspray.method.asset import Asset, read_asset
from matspray.method.masks import read_region
from matspray.presets import asset_stage, get_variant
from matspray.render.backend import rendering_with
from matspray.rundir import RunDir, not_a_run

ENVMAP_SUFFIXES = (".exr", ".hdr")
# A texel further than this from the asset's rendered depth is hidden in that view. The surface is fused from those
# depths (each pixel's blend of its Gaussians' centre depths), so a seen texel lies within a few voxels of them; what
# hides it lies further (the TSDF truncates at 4). Seen fractions per tolerance: docs/dev/export.md.
DEPTH_TOLERANCE_VOXELS = 3.0
BAKE_VIEWS = FIT_VIEWS  # training views the textures are read from, spread over them: as many as the rim fit reads


@dataclass(frozen=True)
class ExportedMesh:
    """A textured mesh in the file's frame, ready to write."""

    positions: np.ndarray  # [V, 3]
    normals: np.ndarray  # [V, 3] unit
    uvs: np.ndarray  # [V, 2] glTF convention
    faces: np.ndarray  # [F, 3] counter-clockwise seen from outside
    textures: np.ndarray  # [S, S, 5] linear base colour rgb, roughness, metallic
    extras: dict  # frame, transforms and settings, for the file's asset.extras
    seconds: dict = field(default_factory=dict)  # per step


def mesh_from_asset(
    asset: Asset,
    cameras: list[Camera],
    config: ExportConfig,
    progress: bool = False,
    notes: dict | None = None,
    region=None,
) -> ExportedMesh:
    """Surface, decimation, atlas and textures of `asset` seen from `cameras` (the training views), bounded by
    `region` (a capture's object region, or None)."""
    seconds, start = {}, time.perf_counter()
    bar = tqdm(total=5, desc="export", disable=not progress, dynamic_ncols=True, postfix="surface")

    def step(name: str, following: str = "") -> None:
        nonlocal start
        now = time.perf_counter()
        seconds[name], start = round(now - start, 2), now
        bar.update()
        # shown now, not at the bar's next refresh: a quick stage's update comes too soon after the last refresh to
        # print, and the next stage would run unnamed (silhouettes, after the decimation's fraction of a second)
        bar.set_postfix_str(following, refresh=True)

    mesh, voxel, alphas = fuse_surface(
        asset.gaussians,
        cameras,
        config.grid,
        config.truncation,
        config.min_alpha,
        config.keep_fraction,
        progress,
        materials=asset.materials.detach(),
        region=region,
    )
    step("surface", "decimate")
    mesh = decimate(mesh, config.faces)
    step("decimate", "silhouettes")
    mesh = fit_silhouettes(mesh, cameras, alphas, config.min_alpha, config.silhouette_rounds, config.normal_smoothing)
    step("silhouettes", "atlas")
    atlas = uv_atlas(mesh, config.texture_size, config.padding)
    step("atlas", "bake")
    materials = asset.materials.detach().cpu().double().numpy()
    textures = bake_textures(
        atlas.positions,
        atlas.faces,
        atlas.uvs,
        asset.gaussians,
        materials,
        config.texture_size,
        config.neighbours,
        voxel,
        bake_views(cameras, config, voxel),
    )
    normals = unit_normals(smoothed_vertex_normals(mesh, config.normal_smoothing), np.asarray(mesh.vertices))[
        atlas.source
    ]
    if config.asset_normals > 0:
        ids, weights = gaussian_weights(atlas.positions, asset.gaussians, config.neighbours, voxel)
        gaussian_normals = asset.normals.detach().cpu().double().numpy()
        normals = blend_normals(ids, weights, gaussian_normals, normals, config.asset_normals)
    step("bake")
    bar.close()
    matrix = file_from_dataset(config.frame)
    extras = {
        **frame_extras(config.frame),
        "voxel": voxel,
        "faces": int(len(atlas.faces)),
        "texture_size": config.texture_size,
        **(notes or {}),
    }
    return ExportedMesh(
        transform_points(matrix, atlas.positions),
        transform_directions(matrix, normals),
        atlas.uvs,
        atlas.faces,
        textures,
        extras,
        seconds,
    )


def bake_views(cameras: list[Camera], config: ExportConfig, voxel: float) -> ViewBake | None:
    """The training views the textures are read from (`config.bake` views), else None: every texel from the
    Gaussians around it (gaussians, and auto where no variant resolved it)."""
    if config.bake != "views":
        return None
    picked = [cameras[i] for i in spread(len(cameras), BAKE_VIEWS)]
    return ViewBake(picked, DEPTH_TOLERANCE_VOXELS * voxel, config.min_alpha)


def resolve_bake(config: ExportConfig, variant: str) -> ExportConfig:
    """`bake` auto: the asset's renders for an asset refined without the 2D maps (no-prior, photos-only), whose
    Gaussians' materials differ from their neighbours' several times more than fused ones do; the Gaussians around
    each texel for the others."""
    if config.bake != "auto":
        return config
    return replace(config, bake="gaussians" if get_variant(variant).uses_maps else "views")


def gltf_material(textures: np.ndarray) -> PbrMaterial:  # [S, S, 5] linear materials
    base = TextureRef(
        encode_base_color(textures[..., :3]).astype(np.float32), wrap_s="clamp", wrap_t="clamp", source="base colour"
    )
    packed = pack_metallic_roughness(textures[..., 3], textures[..., 4]).astype(np.float32)
    return PbrMaterial(
        name="matspray",
        base_color_texture=base,
        metallic_roughness_texture=TextureRef(packed, wrap_s="clamp", wrap_t="clamp", source="metallic-roughness"),
    )


def envmap_paths(out: Path) -> list[Path]:
    """Where the environment map goes beside FILE.glb: FILE_envmap.exr and FILE_envmap.hdr."""
    return [out.with_name(f"{out.stem}_envmap{suffix}") for suffix in ENVMAP_SUFFIXES]


def write_export(mesh: ExportedMesh, out: Path, envmap: Path | None = None) -> list[Path]:
    """The GLB and (when given) the environment map as .exr and .hdr; all or nothing: the maps are written
    to temporary files first and renamed into place only after the GLB is complete."""
    out = Path(out)
    primitive = Primitive("matspray", mesh.positions, mesh.faces, uvs=(mesh.uvs,), normals=mesh.normals, material=0)
    targets = envmap_paths(out) if envmap is not None else []
    temporaries = [atomic_target(path) for path in targets]
    try:
        if envmap is not None:
            rgb, _ = read_image(envmap)
            for tmp in temporaries:
                write_image(tmp, rgb)
        write_glb(out, [primitive], [gltf_material(mesh.textures)], extras={"matspray": mesh.extras})
        for tmp, path in zip(temporaries, targets):
            os.replace(tmp, path)
    finally:
        for tmp in temporaries:
            if tmp.exists():
                tmp.unlink()
    return [out, *targets]


def check_output(out: Path) -> Path:
    """A writable FILE.glb, checked before any work is done."""
    out = Path(out)
    if out.suffix.lower() != ".glb":
        raise ConfigError(f"{out}: the output must be a .glb file")
    check_output_file(out, ".glb")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def run_asset(run_dir: Path, variant: str) -> Path:
    """The asset folder of `variant` in a run, or a RunError that says how to make it."""
    get_variant(variant)  # an unknown variant: one clear line
    if not (run_dir / "dataset.json").exists():
        raise not_a_run(run_dir)
    folder = run_dir / asset_stage(variant)
    if not (folder / "asset.ply").exists():
        raise RunError(
            f"{run_dir}: no asset for variant '{variant}' ({folder.name}/asset.ply); "
            f"make it with `matspray run --variant {variant}`"
        )
    return folder


@dataclass(frozen=True)
class ExportReport:
    files: list[Path]
    faces: int
    vertices: int
    texture_size: int
    seconds: dict


def export_run(
    run_dir,
    out,
    variant: str = "full",
    config: ExportConfig = ExportConfig(),
    data=None,
    progress: bool = True,
    device="cpu",
    backend: str = "torch",
) -> ExportReport:
    """`matspray export`: the run's asset of `variant` as `out` (.glb) plus its environment map. The asset's depth
    renders on `device` with the rasterizer `backend` (both resolved); meshing and baking run on the CPU."""
    run_dir, out = Path(run_dir), check_output(out)
    folder = run_asset(run_dir, variant)
    scene = load_run_scene(RunDir(run_dir), data)
    asset = read_asset(folder, device=device)
    region = read_region(run_dir / "masks")  # a capture without masks: the mesh stays inside its object region
    config = resolve_bake(config, variant)
    with rendering_with(backend):
        mesh = mesh_from_asset(
            asset,
            [view.camera for view in scene.train],
            config,
            progress,
            notes={"variant": variant, "run": str(run_dir.resolve()), "bake": config.bake},
            region=region,
        )
    envmap = folder / "envmap.exr"
    files = write_export(mesh, out, envmap if envmap.exists() else None)
    return ExportReport(files, len(mesh.faces), len(mesh.positions), config.texture_size, mesh.seconds)
