"""`marigold`: Marigold-IID through diffusers, from local weights (`predictors.marigold`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from matspray.predictors.kinds import PredictorKind, register, setting
from matspray.predictors.kinds.files import ENCODING_HELP


@dataclass(frozen=True)
class MarigoldOptions:
    basecolor_encoding: str | None = setting(ENCODING_HELP, metavar="ENC")
    weights: str | None = setting(
        "MarigoldIntrinsicsPipeline folder, or a hub id when the network allows "
        "(default prs-eth/marigold-iid-appearance-v1-1)"
    )
    normals_weights: str | None = setting(
        "MarigoldNormalsPipeline folder (or hub id, e.g. prs-eth/marigold-normals-v1-1): also predict normal maps "
        "(default: none)"
    )
    device: str | None = setting("auto (default: CUDA when available), cpu, cuda or cuda:N")
    steps: int | None = setting("denoising steps (default: the model's)", int)
    ensemble_size: int | None = setting("predictions per view; >= 3 also writes a confidence map (default 1)", int)
    processing_resolution: int | None = setting("resolution the model works at (default: the model's; 0 = native)", int)
    batch_size: int | None = setting("views per model call (default 4)", int)
    seed: int | None = setting("random seed (default 0)", int)


def build(argument: str, options: MarigoldOptions, notify):
    from matspray.predictors.marigold import MarigoldConfig, MarigoldPredictor

    given = {name: value for name, value in asdict(options).items() if value is not None}
    return MarigoldPredictor(MarigoldConfig(**given), notify=notify)


register(
    PredictorKind("marigold", "marigold (diffusers, from --weights)", MarigoldOptions, build, run_flags=("weights",))
)
