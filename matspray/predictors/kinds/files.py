"""`files:DIR`: precomputed maps in the MatSpray, DiffusionRenderer or Marigold layout (`predictors.files`)."""

from __future__ import annotations

from dataclasses import dataclass

from matspray.predictors.kinds import PredictorKind, register, setting

ENCODING_HELP = (
    "how stored base color relates to linear: srgb, gamma1.8 or linear (default: gamma1.8 for DiffusionRenderer "
    "output, srgb otherwise)"
)


@dataclass(frozen=True)
class FilesOptions:
    basecolor_encoding: str | None = setting(ENCODING_HELP, metavar="ENC")


def build(argument: str, options: FilesOptions, notify):
    from matspray.predictors.files import FilesPredictor

    return FilesPredictor(argument, options.basecolor_encoding, notify=notify)


register(
    PredictorKind(
        "files",
        "files:DIR (precomputed maps: MatSpray, DiffusionRenderer or Marigold layout)",
        FilesOptions,
        build,
        argument="the folder holding the maps, e.g. files:outputs/diffusion_renderer",
        reruns_for_eval=True,
    )
)
