"""2D material predictors: per-view base color, roughness and metallic maps from any source.

`predict_views(views, predictor)` is the one entry point; `make_predictor("files:DIR" | "marigold" |
"simulated" | "ground-truth")` builds a predictor (the kinds declare themselves in `predictors.kinds`);
`write_materials2d` / `read_materials2d` are the `RUN/materials2d/` folder that later stages read. Maps may carry a
normal map (`MaterialMaps.normals`, in camera or world space; `world_normals` brings either to world space;
conventions in `normalmaps`).

The names below load on first use, so that `matspray.predictors.kinds` (the declarations the command line reads) is
importable without torch.
"""

import importlib

# the 2D maps' channels, by the names their files, the evaluation's metrics and the docs' tables use (here, without
# torch, for what only names them)
CHANNELS = ("basecolor", "roughness", "metallic")

_WHERE = {
    "matspray.predictors.base": ("Predictor", "predict_views"),
    "matspray.predictors.encodings": ("BASECOLOR_ENCODINGS", "decode_basecolor", "encode_basecolor"),
    "matspray.predictors.maps": (
        "MATERIALS2D",
        "MaterialMaps",
        "maps_to_tensor",
        "predicted_normal_maps",
        "read_materials2d",
        "read_predictor_info",
        "without_normals",
        "world_normals",
        "write_materials2d",
    ),
    "matspray.predictors.kinds": ("AUTO_PREDICTOR", "NO_PREDICTOR", "PredictorSpec"),
    "matspray.predictors.registry": (
        "PredictorOptions",
        "make_predictor",
        "options_for_dataset",
        "predictor_specs",
        "resolve_predictor",
    ),
}
_MODULE_OF = {name: module for module, names in _WHERE.items() for name in names}
__all__ = sorted([*_MODULE_OF, "CHANNELS"])


def __getattr__(name: str):
    if name not in _MODULE_OF:
        raise AttributeError(f"module 'matspray.predictors' has no attribute '{name}'")
    return getattr(importlib.import_module(_MODULE_OF[name]), name)


def __dir__():
    return __all__
