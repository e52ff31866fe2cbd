"""The page's data: the asset quantised into compact arrays, and the lights at the page's resolution.

Per Gaussian, 32 bytes before compression: position 3 x 16 bit over the asset's box, log scale 3 x 16 bit over the
asset's range, rotation 4 x 16 bit (signed, unit quaternion), opacity 8 bit, base colour 3 x 8 bit sRGB-encoded (as
glTF textures store it), roughness and metallic 8 bit each, normal 3 x 16 bit (signed). The arrays are laid end to
end (4-byte aligned), deflated (zlib) and base64-encoded into a script, which a page opened from file:// may load
where it may not fetch. `unpack_asset` reads them back as the page does (src/data.js), for the tests.
"""

from __future__ import annotations

import base64
import json
import zlib

import numpy as np
import torch

from matspray.method.asset import Asset
from matspray.render.shade.brdf_lut import brdf_lut
from matspray.render.shade.envmap import downsample_latlong

LIGHT_HEIGHT = 32  # rows of the page's lights: the page's frame is `matspray relight --env-height 32`'s
TEXTURE_WIDTH = 2048  # texels per row of the page's splat textures
U16, I16, U8 = 65535.0, 32767.0, 255.0


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 1e-12), 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)


def _bounds(values: np.ndarray, axis=None) -> tuple[np.ndarray, np.ndarray]:
    low, high = values.min(axis=axis), values.max(axis=axis)
    return low, np.maximum(high, low + 1e-6)


def _unit(values, low, high) -> np.ndarray:  # -> [0, 1]
    return (values - low) / (high - low)


def quantise_asset(asset: Asset) -> tuple[dict, dict[str, np.ndarray]]:
    """The page's arrays {name: integer array} and what reading them needs (`meta`)."""
    g = asset.gaussians.detach().to("cpu", torch.float64)
    means, log_scales = g.means.numpy(), g.log_scales.numpy()
    materials = asset.materials.detach().cpu().double().numpy()
    normals = torch.nn.functional.normalize(asset.normals.detach().cpu().double(), dim=-1).numpy()
    low, high = _bounds(means, axis=0)
    scale_low, scale_high = _bounds(log_scales)
    u16 = lambda x: np.round(np.clip(x, 0, 1) * U16).astype(np.uint16).reshape(-1)  # noqa: E731
    i16 = lambda x: np.round(np.clip(x, -1, 1) * I16).astype(np.int16).reshape(-1)  # noqa: E731
    u8 = lambda x: np.round(np.clip(x, 0, 1) * U8).astype(np.uint8).reshape(-1)  # noqa: E731
    arrays = {
        "position": u16(_unit(means, low, high)),
        "logScale": u16(_unit(log_scales, scale_low, scale_high)),
        "rotation": i16(g.rotations.numpy()),
        "opacity": u8(g.opacities.numpy()),
        "baseColor": u8(srgb_encode(materials[:, :3])),
        "roughness": u8(materials[:, 3]),
        "metallic": u8(materials[:, 4]),
        "normal": i16(normals),
    }
    meta = {
        "count": len(g),
        "textureWidth": TEXTURE_WIDTH,
        "positionMin": low.tolist(),
        "positionMax": high.tolist(),
        "logScaleMin": float(scale_low),
        "logScaleMax": float(scale_high),
    }
    return meta, arrays


def unpack_asset(meta: dict, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """What the page decodes (src/data.js `decodeSplats`), float64: means, scales, rotations (w, x, y, z, unit),
    opacities, base colour (linear), roughness, metallic, normals."""
    low, high = np.array(meta["positionMin"]), np.array(meta["positionMax"])
    rotations = np.maximum(arrays["rotation"].reshape(-1, 4) / I16, -1)
    span = meta["logScaleMax"] - meta["logScaleMin"]
    return {
        "means": low + arrays["position"].reshape(-1, 3) / U16 * (high - low),
        "scales": np.exp(meta["logScaleMin"] + arrays["logScale"].reshape(-1, 3) / U16 * span),
        "rotations": rotations / np.linalg.norm(rotations, axis=1, keepdims=True),
        "opacities": arrays["opacity"] / U8,
        "base_color": srgb_decode(arrays["baseColor"].reshape(-1, 3) / U8),
        "roughness": arrays["roughness"] / U8,
        "metallic": arrays["metallic"] / U8,
        "normals": np.maximum(arrays["normal"].reshape(-1, 3) / I16, -1),
    }


TYPES = {np.dtype(np.uint8): "u8", np.dtype(np.uint16): "u16", np.dtype(np.int16): "i16", np.dtype(np.float32): "f32"}


def deflated(arrays: dict[str, np.ndarray]) -> tuple[dict, str]:
    """The arrays end to end, each at a 4-byte boundary, deflated and base64-encoded, and where each lies."""
    blob, layout = bytearray(), {}
    for name, values in arrays.items():
        blob.extend(b"\0" * (-len(blob) % 4))
        layout[name] = {"type": TYPES[values.dtype], "offset": len(blob), "length": int(values.size)}
        blob.extend(np.ascontiguousarray(values).astype(values.dtype.newbyteorder("<")).tobytes())
    return layout, base64.b64encode(zlib.compress(bytes(blob), 9)).decode("ascii")


def script(variable: str, value: dict) -> str:
    return f"window.{variable} = {json.dumps(value, separators=(',', ':'))};\n"


def asset_script(asset: Asset, view: dict, notes: dict | None = None) -> str:
    """The page's asset script: the quantised arrays, what reading them needs, the orbit `view` and `notes`."""
    meta, arrays = quantise_asset(asset)
    layout, data = deflated(arrays)
    return script("MATSPRAY_ASSET", {"meta": {**meta, **(notes or {}), "view": view, "arrays": layout}, "data": data})


def page_light(map: torch.Tensor) -> np.ndarray:  # [H, 2H, 3] linear -> [LIGHT_HEIGHT, 2 LIGHT_HEIGHT, 3] float32
    """A light as the page holds it: `EnvironmentMap.from_tensor(map, LIGHT_HEIGHT)`'s area downsampling (the page
    floors it at MIN_RADIANCE, as from_tensor does)."""
    return downsample_latlong(map.detach().cpu().float(), LIGHT_HEIGHT).numpy().astype(np.float32)


def lights_script(lights: list[tuple[str, torch.Tensor]]) -> str:
    """The named lights (linear lat-long maps, any size) and the split-sum table (32 x 32, A and B)."""
    maps = {name: page_light(map) for name, map in lights}
    arrays = {name: map.reshape(-1) for name, map in maps.items()}
    lut = brdf_lut(32, dtype=torch.float32).numpy()  # [n.v, r, 2]
    arrays["lut"] = np.concatenate([lut, np.zeros_like(lut)], axis=-1).astype(np.float32).reshape(-1)  # RGBA texels
    layout, data = deflated(arrays)
    names, heights = list(maps), [int(map.shape[0]) for map in maps.values()]  # a smaller light keeps its rows
    return script(
        "MATSPRAY_LIGHTS", {"height": LIGHT_HEIGHT, "names": names, "heights": heights, "arrays": layout, "data": data}
    )
