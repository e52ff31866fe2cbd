"""`simulated[:MODEL]`: ground-truth maps turned into diffusion-like, view-inconsistent predictions by an error model
(`predictors.simulated`, `predictors.error_models`; benchmarks only, labelled as simulated in every output)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from matspray.predictors.kinds import PredictorKind, register, setting


@dataclass(frozen=True)
class SimulatedOptions:
    batch_size: int | None = setting("views per window (default 8)", int)
    seed: int | None = setting("random seed (default: the synth object's seed, 0 for other data)", int)
    severity: float | None = setting("strength of the simulated failure modes; 0 = ground truth (default 1)", float)


def build(argument: str, options: SimulatedOptions, notify):
    from matspray.predictors.error_models import DEFAULT_MODEL, error_model
    from matspray.predictors.simulated import SimulatedPredictor

    given = {name: value for name, value in asdict(options).items() if value is not None}
    return SimulatedPredictor(error_model(argument or DEFAULT_MODEL, **given))


register(
    PredictorKind(
        "simulated",
        "simulated[:paper|harsh|outliers|dr] (an error model; plain simulated = paper)",
        SimulatedOptions,
        build,
        argument="optional",
        needs_ground_truth=True,
        object_seed=True,
        reruns_for_eval=True,
        run_hidden=("severity",),
    )
)
