"""The relightable asset as KHR_gaussian_splatting glTF (`matspray export --splats FILE.glb`) and back.

Any implementation of the extension draws the splats' spherical harmonics, so the colour is baked: each Gaussian
shaded under one light (`render.shade.deferred.shade`, as `matspray relight` shades) from BAKE_DIRECTIONS directions
around it, sRGB-encoded (the file's colour space is display-referred sRGB) and fitted by least squares with
spherical harmonics of degree BAKE_DEGREE. The materials, normals and the estimated light travel beside them
(`gltf.splats`), so that MatSpray reads the file back as the asset it was: `read_splats_asset`.

The file is in glTF's Y-up frame (`export.frames`: (x, y, z)_dataset -> (x, z, -y)_glTF); its light stays a lat-long
map about the dataset's +Z (`render.latlong`), and the asset's extras say so.
"""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.errors import file_error
from matspray.export.frames import GLTF_FROM_DATASET, frame_extras
from matspray.gaussians import Gaussians
from matspray.gltf.splats import (
    SplatFile,
    read_splats_glb,
    tileset,
    write_bytes_atomic,
    write_splats_glb,
    write_spz_glb,
)
from matspray.method.asset import Asset
from matspray.render.shade.deferred import shade
from matspray.render.shade.sh import sh_basis

BAKE_DEGREE = 3  # the highest the extension defines: the specular highlights move with the view
BAKE_DIRECTIONS = 64  # view directions per Gaussian the fit sees (a degree-3 fit has 16 unknowns)
MIN_OPACITY = 2.0**-24  # opacities are held off 0 and 1 when read back, so that their logits are finite


@dataclass
class SplatsAsset:
    """A splats glb read back: the asset in the dataset's frame, its light and the view it was exported with."""

    asset: Asset
    light: Tensor | None  # [H, 2H, 3] linear lat-long, dataset frame
    view: dict  # `web.orbit.orbit_spec` of the run, {} when the file has none


def fibonacci_directions(count: int) -> Tensor:  # -> [count, 3] unit, spread evenly over the sphere, float64
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    rho = torch.sqrt(1.0 - z * z)
    return torch.stack([rho * torch.cos(phi), rho * torch.sin(phi), z], dim=-1)


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:  # [3, 3] rotation with trace > -1 -> [4] (w, x, y, z)
    w = math.sqrt(max(1.0 + np.trace(m), 1e-12)) / 2
    return np.array([w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)])


def quaternion_product(a: Tensor, b: Tensor) -> Tensor:  # [..., 4] (w, x, y, z) x2 -> [..., 4] a b
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def rotate_sh(sh: Tensor, rotation: Tensor) -> Tensor:  # [N, K, 3], [3, 3] -> [N, K, 3]
    """Coefficients of the same colours in a frame turned by `rotation` (new d' = rotation d): the colours at
    BAKE_DIRECTIONS directions refitted, exact since each degree's span is closed under rotations."""
    degree = int(round(sh.shape[1] ** 0.5)) - 1
    directions = fibonacci_directions(BAKE_DIRECTIONS)
    old = sh_basis(directions, degree)  # [D, K]
    new = sh_basis(directions @ rotation.double().T, degree)
    return torch.einsum("kd,de,nec->nkc", torch.linalg.pinv(new), old, sh.double()).to(sh.dtype)


def bake_sh(asset: Asset, light, degree: int = BAKE_DEGREE, chunk: int = 1 << 14) -> Tensor:  # -> [N, K, 3]
    """Spherical harmonics [N, (degree + 1)^2, 3] whose colour seen along d (camera to Gaussian) is the sRGB-encoded
    radiance of the Gaussian shaded under `light` (a PrefilteredEnvironment) for the view -d, least squares over
    BAKE_DIRECTIONS directions."""
    directions = fibonacci_directions(BAKE_DIRECTIONS).to(asset.materials)  # [D, 3]
    fit = torch.linalg.pinv(sh_basis(directions.double(), degree)).to(asset.materials)  # [K, D]
    out = []
    for start in range(0, len(asset.normals), chunk):
        m = asset.materials[start : start + chunk, None, :].expand(-1, len(directions), 5)  # [n, D, 5]
        n = asset.normals[start : start + chunk, None, :].expand(-1, len(directions), 3)
        rgb = shade(m[..., :3], m[..., 3], m[..., 4], n, -directions.expand_as(n), light)  # [n, D, 3]
        out.append(torch.einsum("kd,ndc->nkc", fit, linear_to_srgb(rgb.clamp(0.0, 1.0)) - 0.5))
    return torch.cat(out)


def asset_to_splats(asset: Asset, light, estimated: Tensor | None, view: dict | None = None) -> SplatFile:
    """The asset in glTF's frame, its colour baked under `light` (PrefilteredEnvironment), with the `estimated`
    light [H, 2H, 3] (dataset frame) beside it."""
    rotation = torch.as_tensor(GLTF_FROM_DATASET[:3, :3], dtype=torch.float64)
    g = asset.gaussians.detach().to("cpu", torch.float64)
    turn = torch.as_tensor(matrix_to_quaternion(GLTF_FROM_DATASET[:3, :3]), dtype=torch.float64)
    quats = quaternion_product(turn.expand_as(g.quats), g.rotations)  # (w, x, y, z) in the file's frame
    sh = bake_sh(asset, light).detach().cpu().double()
    numpy = lambda t: t.detach().cpu().numpy()  # noqa: E731
    materials = asset.materials.detach().cpu()
    return SplatFile(
        positions=numpy(g.means @ rotation.T),
        rotations=numpy(quats[:, [1, 2, 3, 0]]),
        scales=numpy(g.scales),
        opacities=numpy(g.opacities),
        sh=numpy(rotate_sh(sh, rotation)),
        base_color=numpy(materials[:, :3].clamp(0, 1)),
        roughness=numpy(materials[:, 3].clamp(0, 1)),
        metallic=numpy(materials[:, 4].clamp(0, 1)),
        normals=numpy(torch.nn.functional.normalize(asset.normals.detach().cpu().double(), dim=-1) @ rotation.T),
        light=None if estimated is None else numpy(estimated.detach().float()),
        extras={"light_frame": "dataset (+Z up), matspray.render.latlong", "view": view or {}},
    )


def write_splats(path, asset: Asset, light, estimated: Tensor | None, view: dict | None = None) -> list[Path]:
    """FILE.glb (the splats and MatSpray's materials) and, where gsply is installed, FILE_3dtiles/ (the splats
    SPZ-compressed in a one-tile 3D Tiles tileset: what CesiumJS draws); returns the files written."""
    path = Path(path)
    splats = asset_to_splats(asset, light, estimated, view)
    write_splats_glb(path, splats, asset_extras={"matspray": frame_extras("gltf")})
    try:
        spz = spz_bytes(splats)
    except ImportError:
        return [path]
    tiles = path.with_name(f"{path.stem}_3dtiles")
    tiles.mkdir(parents=True, exist_ok=True)
    write_spz_glb(tiles / "splats.glb", splats, spz)
    radius = float(np.linalg.norm(splats.positions, axis=1).max() + 3 * splats.scales.max())
    (tiles / "tileset.json").write_text(json.dumps(tileset("splats.glb", radius), indent=1))
    return [path, tiles / "tileset.json", tiles / "splats.glb"]


def spz_bytes(splats: SplatFile) -> bytes:
    """The splats as a Niantic SPZ stream (version 3: gzip, 12 fractional bits of position) by gsply; ImportError
    without it."""
    from gsply import GSData, write_spz

    opacity = np.clip(splats.opacities, MIN_OPACITY, 1 - MIN_OPACITY)
    data = GSData(
        means=splats.positions.astype(np.float32),
        scales=np.log(np.maximum(splats.scales, 1e-30)).astype(np.float32),
        quats=splats.rotations[:, [3, 0, 1, 2]].astype(np.float32),  # SPZ's (w, x, y, z)
        opacities=np.log(opacity / (1 - opacity)).astype(np.float32),
        sh0=splats.sh[:, 0].astype(np.float32),
        shN=splats.sh[:, 1:].astype(np.float32),
    )
    with tempfile.TemporaryDirectory() as folder:
        write_spz(Path(folder) / "splats.spz", data, version=3)
        return (Path(folder) / "splats.spz").read_bytes()


def write_spz_file(path, asset: Asset, light, estimated: Tensor | None = None, view: dict | None = None) -> list[Path]:
    """FILE.spz: the splats alone, their colour baked under `light` as in the glb (no materials: SPZ has no place for
    them), for SuperSplat, Spark and other SPZ readers. SPZ's own axes are glTF's (right, up, back), so the glb's
    splats go in as they are. Raises ImportError without gsply."""
    path = Path(path)
    write_bytes_atomic(path, spz_bytes(asset_to_splats(asset, light, estimated, view)))
    return [path]


def read_splats_asset(path, device="cpu") -> SplatsAsset:
    """A glb written by `write_splats` as the asset it holds (materials and normals required)."""
    path = Path(path)
    splats, matrix = read_splats_glb(path)
    if not splats.has_materials:
        raise file_error(
            path,
            "has Gaussian splats but no MatSpray materials (_BASECOLOR, _ROUGHNESS, _METALLIC, _NORMAL)",
            "only files from `matspray export --splats` can be relit",
        )
    if not np.allclose(matrix, np.eye(4)):
        raise file_error(path, "places its splats with a node transform", "MatSpray reads only its own splat files")
    back = torch.as_tensor(GLTF_FROM_DATASET[:3, :3].T, dtype=torch.float64)  # file -> dataset
    tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    turn = torch.as_tensor(matrix_to_quaternion(back.numpy()), dtype=torch.float64)
    quats = quaternion_product(turn.expand(len(splats.rotations), 4), tensor(splats.rotations)[:, [3, 0, 1, 2]])
    opacity = tensor(splats.opacities).clamp(MIN_OPACITY, 1 - MIN_OPACITY)
    gaussians = Gaussians(
        means=tensor(splats.positions) @ back.T,
        log_scales=tensor(splats.scales).clamp_min(1e-30).log(),
        quats=quats,
        opacity_logits=torch.logit(opacity),
        sh=rotate_sh(tensor(splats.sh), back),
    ).to(device, torch.float32)
    materials = torch.cat(
        [tensor(splats.base_color), tensor(splats.roughness)[:, None], tensor(splats.metallic)[:, None]], 1
    )
    normals = torch.nn.functional.normalize(tensor(splats.normals) @ back.T, dim=-1)
    asset = Asset(gaussians, materials.to(device, torch.float32), normals.to(device, torch.float32))
    light = None if splats.light is None else torch.as_tensor(splats.light, device=device)
    return SplatsAsset(asset, light, dict(splats.extras.get("view", {})))
