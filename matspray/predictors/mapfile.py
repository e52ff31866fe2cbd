"""One material map file in, with the checks every source needs: readable, the right channels,
values in [0, 1]. Stored values are returned as they are (no colour decoding)."""

from __future__ import annotations

from pathlib import Path

from torch import Tensor

from matspray.data.images import read_raw
from matspray.errors import MatsprayError, file_error

MAP_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".npy")
RANGE_TOLERANCE = 1.0 / 512.0  # float files may overshoot [0, 1] by rounding; more than this is an error
GREY_TOLERANCE = 0.04  # mean channel spread above which a "grey" 3-channel map is really a colour image


def read_values(path: Path) -> Tensor:  # [H, W, C] stored values, checked to lie in [0, 1]
    try:
        values = read_raw(path)
    except MatsprayError:
        raise
    except Exception as exc:  # decoders raise their own types for truncated or corrupt files (e.g. png.FormatError)
        raise file_error(path, f"cannot read image: {exc}") from None
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
