"""The light models refinement can learn, by their `refine.light_model` name (`light.Light` is their interface)."""

from __future__ import annotations

from matspray.errors import ConfigError
from matspray.render.shade.envmap import EnvironmentMap
from matspray.render.shade.light import Light
from matspray.render.shade.sg import SGLight

LIGHT_MODELS: dict[str, type[Light]] = {model.kind: model for model in (EnvironmentMap, SGLight)}


def light_model(name: str) -> type[Light]:
    if name not in LIGHT_MODELS:
        raise ConfigError(f"unknown light model '{name}'; choose one of {', '.join(LIGHT_MODELS)}")
    return LIGHT_MODELS[name]


def load_light(path) -> Light:
    """The light saved at `path` (an asset's `envmap.exr`), read as the model that wrote it: the first model (in
    reverse order: the lat-long map, whose file every model also writes, last) that finds its files there."""
    for model in reversed(LIGHT_MODELS.values()):
        if model.saved_at(path):
            return model.load(path)
    return EnvironmentMap.load(path)  # says which file is missing
