"""One material map file in, with the checks every source needs: readable, the right channels,
values in [0, 1]. Stored values are returned as they are (no colour decoding). Normal maps are vectors,
not values in [0, 1]: `read_normal_map` decodes and checks them."""

from __future__ import annotations

from pathlib import Path

from torch import Tensor

from matspray.data.images import read_raw
from matspray.errors import MatsprayError, file_error
from matspray.predictors.normalmaps import decode_png_normals, normal_problem, renormalised

MAP_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".npy")
NORMAL_SUFFIXES = (".png", ".exr", ".npy")  # PNG stores n * 0.5 + 0.5; EXR and NPY the vectors themselves
NORMAL_HINT = "a PNG normal map stores n * 0.5 + 0.5 per channel (8 or 16 bit); EXR and NPY hold the unit vectors"
RANGE_TOLERANCE = 1.0 / 512.0  # float files may overshoot [0, 1] by rounding; more than this is an error
GREY_TOLERANCE = 0.04  # mean channel spread above which a "grey" 3-channel map is really a colour image


def read_stored(path: Path) -> Tensor:  # [H, W, C] as stored (LDR scaled to [0, 1])
    try:
        return read_raw(path)
    except MatsprayError:
        raise
    except Exception as exc:  # decoders raise their own types for truncated or corrupt files (e.g. png.FormatError)
        raise file_error(path, f"cannot read image: {exc}") from None


def read_values(path: Path) -> Tensor:  # [H, W, C] stored values, checked to lie in [0, 1]
    values = read_stored(path)
    low, high = float(values.min()), float(values.max())
    if low < -RANGE_TOLERANCE or high > 1.0 + RANGE_TOLERANCE:
        raise file_error(
            path, f"values outside [0, 1] (min {low:.4g}, max {high:.4g})", "material maps must be normalised to [0, 1]"
        )
    return values.clamp(0.0, 1.0)


def drop_alpha(values: Tensor, path: Path, wanted: str) -> Tensor:  # [H, W, C] -> [H, W, C'] without an alpha channel
    channels = values.shape[-1]
    if channels in (2, 4):
        return values[..., : channels - 1]
    if channels in (1, 3):
        return values
    raise file_error(path, f"has {channels} channels; a {wanted} map needs 1 (grey) or 3 (RGB), optionally with alpha")


def read_color_map(path: Path) -> Tensor:  # [H, W, 3] stored values
    values = drop_alpha(read_values(path), path, "base color")
    if values.shape[-1] != 3:
        raise file_error(path, "is a single-channel image; a base color map needs 3 channels (RGB)")
    return values


def read_scalar_map(path: Path, what: str) -> Tensor:  # [H, W]
    """A roughness / metallic / confidence map: grey, or RGB with equal channels (as many tools save them)."""
    values = drop_alpha(read_values(path), path, what)
    if values.shape[-1] == 1:
        return values[..., 0]
    spread = float((values.max(-1).values - values.min(-1).values).mean())
    if spread > GREY_TOLERANCE:
        raise file_error(
            path,
            f"is a colour image (channels differ by {spread:.3f} on average), "
            f"but a {what} map holds one value per pixel",
            "save it as a grey image, or check that the file is the right pass",
        )
    return values.mean(-1)


def read_packed_map(path: Path, names: tuple[str, ...]) -> dict[str, Tensor]:  # name -> [H, W]
    """Several scalar maps packed into the channels of one file, e.g. ("roughness", "metallic") in R and G."""
    values = read_values(path)
    if values.shape[-1] < len(names):
        raise file_error(
            path, f"has {values.shape[-1]} channel(s); expected {', '.join(names)} in the first {len(names)} channels"
        )
    return {name: values[..., i].contiguous() for i, name in enumerate(names)}


def read_normal_map(path: Path) -> Tensor:  # [H, W, 3] unit vectors, 0 where there is none; in the file's space
    """A normal map file: PNG decoded from n * 0.5 + 0.5 (black or alpha-0 pixels hold no normal), EXR/NPY
    read as vectors (zero, or alpha 0, for none); checked to be [H, W, 3(+alpha)] of unit vectors."""
    suffix = path.suffix.lower()
    if suffix not in NORMAL_SUFFIXES:
        raise file_error(path, f"is a {suffix} file, but a normal map must be PNG, EXR or NPY", NORMAL_HINT)
    values = read_stored(path)
    channels = values.shape[-1]
    if values.ndim != 3 or channels not in (3, 4):
        raise file_error(path, f"has {channels} channel(s); a normal map needs 3 (x, y, z), optionally with alpha")
    if suffix == ".png":
        vectors = decode_png_normals(values)
    else:
        vectors = values[..., :3] if channels == 3 else values[..., :3] * (values[..., 3:] > 0)
    problem = normal_problem(vectors)
    if problem:
        raise file_error(path, problem, NORMAL_HINT)
    return renormalised(vectors)
