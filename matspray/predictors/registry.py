"""`--predictor SPEC` -> a Predictor, by the kinds declared in `matspray.predictors.kinds` (`files:DIR`, `marigold`,
`simulated[:MODEL]`, `ground-truth`, and any kind registered there)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from matspray.data.formats.blender import read_scene_json
from matspray.errors import DataError, SettingError
from matspray.predictors.base import Predictor
from matspray.predictors.ground_truth import check_ground_truth
from matspray.predictors.kinds import (
    AUTO_PREDICTOR,
    NO_PREDICTOR,
    PredictorKind,
    PredictorSpec,
    option_fields,
    predictor_kinds,
)

__all__ = ["AUTO_PREDICTOR", "NO_PREDICTOR", "PredictorOptions", "make_predictor", "predictor_specs"]


def predictor_specs() -> tuple[str, ...]:
    """The spec of every kind, as its help names it, and none."""
    return (*(kind.usage.split(" (")[0] for kind in predictor_kinds().values()), NO_PREDICTOR)


class PredictorOptions:
    """The predictor options given, by name (a field of some kind's options; None: the predictor's default). An
    unknown name is a TypeError, as a dataclass's would be."""

    def __init__(self, **given):
        known = option_fields()
        unknown = sorted(set(given) - set(known))
        if unknown:
            raise TypeError(f"unknown predictor options: {', '.join(unknown)} (known: {', '.join(known)})")
        # the given values are the instance's attributes, so `vars(options)` is what was given (`stages.predict_maps`)
        vars(self).update({name: value for name, value in given.items() if value is not None})

    def __getattr__(self, name: str):  # an option not given: None (the predictor's default)
        if name in option_fields():
            return None
        raise AttributeError(name)

    @property
    def given(self) -> dict:
        return dict(vars(self))

    def __eq__(self, other) -> bool:
        return isinstance(other, PredictorOptions) and self.given == other.given

    def __repr__(self) -> str:
        return f"PredictorOptions({', '.join(f'{k}={v!r}' for k, v in sorted(self.given.items()))})"

    def replace(self, **changes) -> PredictorOptions:
        return PredictorOptions(**{**self.given, **changes})


def object_seed(data) -> int | None:
    """The seed a `matspray synth` object was made with (its scene.json), or None for other datasets."""
    seed = (read_scene_json(Path(data)) or {}).get("seed") if data is not None else None
    return seed if isinstance(seed, int) and not isinstance(seed, bool) else None


def declared_kind(spec: PredictorSpec) -> PredictorKind | None:
    return predictor_kinds().get(spec.kind)


def options_for_dataset(spec: str, options: PredictorOptions, data) -> PredictorOptions:
    """`options` for predicting the views of the dataset folder `data`: a kind that draws from the object's seed
    (simulated) given no `seed` draws its errors from the synth object's own seed, so that the objects of a benchmark
    (made with seeds 0, 1, ...) get independent errors rather than one draw repeated on every object (the views of
    every synth object have the same names). Object seed 0 gives the error model's default draws."""
    kind = declared_kind(PredictorSpec.parse(spec))
    if kind is None or not kind.object_seed or options.seed is not None:
        return options
    seed = object_seed(data)
    return options if seed is None else options.replace(seed=seed)


def resolve_predictor(spec: str, views: list, notify: Callable[[str], None] = print) -> str:
    """The predictor a run uses for the training `views`: `auto` becomes simulated where every view has ground-truth
    maps, else none (said in one line). A predictor that needs ground truth on views without it is refused here,
    before any training, naming the dataset and the views."""
    parsed = PredictorSpec.parse(spec)
    if parsed.kind == AUTO_PREDICTOR:
        try:
            check_ground_truth(views)
        except DataError:
            notify(
                "predictor: this dataset has no ground-truth maps, so the run makes the photos-only asset without 2D "
                "maps (give --predictor files:DIR or marigold for the full method)"
            )
            return NO_PREDICTOR
        return "simulated"
    kind = declared_kind(parsed)
    if kind is not None and kind.needs_ground_truth:
        check_ground_truth(views)
    return spec


def checked_kind(spec: PredictorSpec, text: str) -> PredictorKind:
    """The kind of a spec that names one, with the ':' argument it takes; a SettingError otherwise."""
    if spec.kind == NO_PREDICTOR:
        raise SettingError(
            "predictor", "'none' predicts no maps; only a run refines without them (no-prior, photos-only)"
        )
    kind = declared_kind(spec)
    if kind is None:
        raise SettingError("predictor", f"unknown predictor '{text}'; use one of {', '.join(predictor_specs())}")
    if kind.argument not in ("", "optional") and not spec.argument:
        raise SettingError("predictor", f"{kind.usage.split(' (')[0]} needs {kind.argument}")
    if not kind.argument and spec.argument:
        raise SettingError("predictor", f"{kind.name} takes no ':' argument (got '{text}')")
    return kind


def make_predictor(
    spec: str, options: PredictorOptions | None = None, notify: Callable[[str], None] = print
) -> Predictor:
    options = options or PredictorOptions()
    parsed = PredictorSpec.parse(spec)
    kind = checked_kind(parsed, str(spec))
    unused = sorted(name for name in options.given if name not in kind.option_names)
    if unused:
        others = f" (nor do {', '.join(unused[1:])})" if len(unused) > 1 else ""
        raise SettingError(unused[0], f"does not apply to the {kind.name} predictor{others}")
    return kind.build(parsed.argument, kind.options(**options.given), notify)
