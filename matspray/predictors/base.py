"""The one interface every material source implements, and `predict_views`, which every caller uses."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import Counter
from typing import Callable

from matspray.data.scene import View
from matspray.errors import DataError
from matspray.predictors.maps import MaterialMaps


class Predictor(ABC):
    """Turns views into per-view material maps (any resolution; `predict_views` fits them to the views)."""

    name: str = ""
    simulated: bool = False  # derived from ground truth to imitate a model (benchmarks only)
    benchmark_only: bool = False  # needs ground truth: not usable on real captures

    @abstractmethod
    def predict(self, views: list[View]) -> dict[str, MaterialMaps]:
        """Maps for each view, keyed by view name."""

    def describe(self) -> dict:
        """What produced the maps, for `predictor.json`: name and every setting that matters."""
        return {"predictor": self.name, "simulated": self.simulated, "benchmark_only": self.benchmark_only}


def predict_views(
    views: list[View], predictor: Predictor, notify: Callable[[str], None] = print
) -> dict[str, MaterialMaps]:
    """Material maps for every view in `views` (name -> maps at the view's resolution), in view order.

    Maps from a source with another resolution are resampled, with one notice line per size.
    """
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        repeated = sorted(n for n, c in Counter(names).items() if c > 1)
        raise DataError(f"views must have unique names to receive maps; repeated: {', '.join(repeated[:10])}")
    if not views:
        raise DataError("no views to predict materials for")
    if predictor.simulated:
        notify(
            f"SIMULATED material maps ({predictor.name}): ground truth degraded for benchmarks, not a real prediction"
        )
    elif predictor.benchmark_only:
        notify(f"GROUND-TRUTH material maps ({predictor.name}): the benchmark upper bound, not a prediction")
    raw = predictor.predict(views)
    missing = [n for n in names if n not in raw]
    if missing:
        raise DataError(
            f"the {predictor.name} predictor gave no maps for {len(missing)} view(s): {', '.join(missing[:10])}"
        )
    out, resampled = {}, Counter()
    for view in views:
        maps = raw[view.name].validate(f"{predictor.name} maps of view '{view.name}'")
        if (maps.height, maps.width) != (view.height, view.width):
            resampled[(maps.width, maps.height, view.width, view.height)] += 1
            maps = maps.resized(view.height, view.width)
        out[view.name] = maps
    for (sw, sh, vw, vh), count in resampled.items():
        note = f"notice: {predictor.name} maps are {sw}x{sh}, the views {vw}x{vh}; resampled {count} view(s)"
        if abs(sw / sh - vw / vh) > 0.01:
            note += " (aspect ratios differ: if the model cropped its input, the maps will not line up)"
        notify(note)
    return out
