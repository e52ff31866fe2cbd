"""`ground-truth`: the dataset's own true maps (benchmarks on `matspray synth` objects; `predictors.ground_truth`)."""

from __future__ import annotations

from dataclasses import dataclass

from matspray.predictors.kinds import PredictorKind, register


@dataclass(frozen=True)
class NoOptions:
    pass


def build(argument: str, options: NoOptions, notify):
    from matspray.predictors.ground_truth import GroundTruthPredictor

    return GroundTruthPredictor()


register(
    PredictorKind(
        "ground-truth",
        "ground-truth (benchmarks on `matspray synth` objects only)",
        NoOptions,
        build,
        needs_ground_truth=True,
        reruns_for_eval=True,
    )
)
