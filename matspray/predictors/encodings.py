"""How the values stored in a base color file relate to linear base color.

Material models save base color for display, not as linear reflectance:
- `srgb`: the exact sRGB curve (MatSpray's own files, Marigold's albedo, most tools);
- `gammaG` (e.g. `gamma1.8`): a pure power law, linear = stored ** G. DiffusionRenderer was trained on
  tone-mapped targets; the paper's supplement finds that an inverse gamma of about 1.8 recovers most of
  its base color, so `gamma1.8` is the default for its outputs;
- `linear`: values stored as they are.
Roughness and metallic are always stored linearly.
"""

from __future__ import annotations

import re

from torch import Tensor

from matspray.data.images import linear_to_srgb, srgb_to_linear
from matspray.errors import SettingError

BASECOLOR_ENCODINGS = ("srgb", "gamma1.8", "linear")  # the documented choices; any `gammaG` with G > 0 works
_GAMMA = re.compile(r"^gamma(\d+(?:\.\d*)?|\.\d+)$")


def check_encoding(encoding: str) -> str:
    """The encoding name, normalised; SettingError for anything else."""
    name = str(encoding).strip().lower()
    if name in ("srgb", "linear"):
        return name
    match = _GAMMA.match(name)
    if match and float(match.group(1)) > 0:
        return name
    raise SettingError(
        "basecolor_encoding",
        f"unknown encoding '{encoding}'; use one of {', '.join(BASECOLOR_ENCODINGS)} (or gammaG for another "
        "power law, e.g. gamma2.2)",
    )


def _gamma(encoding: str) -> float:
    return float(_GAMMA.match(encoding).group(1))


def decode_basecolor(stored: Tensor, encoding: str) -> Tensor:  # [..., 3] stored in [0, 1] -> [..., 3] linear
    encoding = check_encoding(encoding)
    stored = stored.clamp(0.0, 1.0)
    if encoding == "srgb":
        return srgb_to_linear(stored)
    if encoding == "linear":
        return stored
    return stored ** _gamma(encoding)


def encode_basecolor(linear: Tensor, encoding: str) -> Tensor:  # [..., 3] linear -> [..., 3] stored in [0, 1]
    encoding = check_encoding(encoding)
    linear = linear.clamp(0.0, 1.0)
    if encoding == "srgb":
        return linear_to_srgb(linear)
    if encoding == "linear":
        return linear
    return linear ** (1.0 / _gamma(encoding))
