"""`--predictor SPEC` -> a Predictor. Specs: `files:DIR`, `marigold`, `simulated[:MODEL]`, `ground-truth`."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Callable

from matspray.data.formats.blender import read_scene_json
from matspray.errors import DataError, SettingError
from matspray.predictors.base import Predictor
from matspray.predictors.error_models import DEFAULT_MODEL, error_model
from matspray.predictors.files import FilesPredictor
from matspray.predictors.ground_truth import GroundTruthPredictor, check_ground_truth
from matspray.predictors.marigold import MarigoldConfig, MarigoldPredictor
from matspray.predictors.simulated import SimulatedPredictor

SPECS = ("files:DIR", "marigold", "simulated[:paper|harsh|outliers|dr]", "ground-truth", "none")
NO_PREDICTOR = "none"  # a run without 2D maps: only the variants that need none (matspray.presets.MAPLESS)
AUTO_PREDICTOR = "auto"  # `run`'s default: simulated where the dataset has ground-truth maps (benchmarks), else none
NEEDS_GROUND_TRUTH = ("simulated", "ground-truth")


@dataclass
class PredictorOptions:
    """Every setting the command line offers; None = the predictor's default. Each predictor takes its own."""

    basecolor_encoding: str | None = None  # files, marigold
    weights: str | None = None  # marigold
    normals_weights: str | None = None  # marigold: its normals model, which adds normal maps
    device: str | None = None  # marigold
    steps: int | None = None  # marigold
    ensemble_size: int | None = None  # marigold
    processing_resolution: int | None = None  # marigold
    batch_size: int | None = None  # marigold, simulated
    seed: int | None = None  # marigold, simulated
    severity: float | None = None  # simulated


USES = {
    "files": {"basecolor_encoding"},
    "marigold": {
        "basecolor_encoding",
        "weights",
        "normals_weights",
        "device",
        "steps",
        "ensemble_size",
        "processing_resolution",
        "batch_size",
        "seed",
    },
    "simulated": {"batch_size", "seed", "severity"},
    "ground-truth": set(),
}


def _given(options: PredictorOptions, names: set[str]) -> dict:
    return {n: getattr(options, n) for n in names if getattr(options, n) is not None}


def object_seed(data) -> int | None:
    """The seed a `matspray synth` object was made with (its scene.json), or None for other datasets."""
    seed = (read_scene_json(Path(data)) or {}).get("seed") if data is not None else None
    return seed if isinstance(seed, int) and not isinstance(seed, bool) else None


def options_for_dataset(spec: str, options: PredictorOptions, data) -> PredictorOptions:
    """`options` for predicting the views of the dataset folder `data`: a simulated predictor given no
    `seed` draws its errors from the synth object's own seed, so that the objects of a benchmark (made
    with seeds 0, 1, ...) get independent errors rather than one draw repeated on every object (the
    views of every synth object have the same names). Object seed 0 gives the error model's default draws."""
    if str(spec).partition(":")[0].strip().lower() != "simulated" or options.seed is not None:
        return options
    seed = object_seed(data)
    return options if seed is None else replace(options, seed=seed)


def resolve_predictor(spec: str, views: list, notify: Callable[[str], None] = print) -> str:
    """The predictor a run uses for the training `views`: `auto` becomes simulated where every view has ground-truth
    maps, else none (said in one line). A predictor that needs ground truth on views without it is refused here,
    before any training, naming the dataset and the views."""
    kind = str(spec).partition(":")[0].strip().lower()
    if kind == AUTO_PREDICTOR:
        try:
            check_ground_truth(views)
        except DataError:
            notify(
                "predictor: this dataset has no ground-truth maps, so the run makes the no-prior asset without 2D maps "
                "(give --predictor files:DIR or marigold for the full method)"
            )
            return NO_PREDICTOR
        return "simulated"
    if kind in NEEDS_GROUND_TRUTH:
        check_ground_truth(views)
    return spec


def make_predictor(
    spec: str, options: PredictorOptions | None = None, notify: Callable[[str], None] = print
) -> Predictor:
    options = options or PredictorOptions()
    if spec == NO_PREDICTOR:
        raise SettingError(
            "predictor", "'none' predicts no maps; only a run refines without them (the no-prior variant)"
        )
    kind, _, argument = str(spec).partition(":")
    kind = kind.strip().lower()
    if kind not in USES:
        raise SettingError("predictor", f"unknown predictor '{spec}'; use one of {', '.join(SPECS)}")
    if kind == "files" and not argument:
        raise SettingError(
            "predictor", "files:DIR needs the folder holding the maps, e.g. files:outputs/diffusion_renderer"
        )
    if kind not in ("files", "simulated") and argument:
        raise SettingError("predictor", f"{kind} takes no ':' argument (got '{spec}')")
    unused = sorted(n for n in _given(options, {f.name for f in fields(options)}) if n not in USES[kind])
    if unused:
        others = f" (nor do {', '.join(unused[1:])})" if len(unused) > 1 else ""
        raise SettingError(unused[0], f"does not apply to the {kind} predictor{others}")
    if kind == "files":
        return FilesPredictor(argument, options.basecolor_encoding, notify=notify)
    if kind == "marigold":
        return MarigoldPredictor(MarigoldConfig(**_given(options, USES["marigold"])), notify=notify)
    if kind == "simulated":
        return SimulatedPredictor(error_model(argument.strip() or DEFAULT_MODEL, **_given(options, USES["simulated"])))
    return GroundTruthPredictor()
