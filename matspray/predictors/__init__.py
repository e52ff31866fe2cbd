"""2D material predictors: per-view base color, roughness and metallic maps from any source.

`predict_views(views, predictor)` is the one entry point; `make_predictor("files:DIR" | "marigold" |
"simulated" | "ground-truth")` builds a predictor; `write_materials2d` / `read_materials2d` are the
`RUN/materials2d/` folder that later stages read. Maps may carry a normal map (`MaterialMaps.normals`, in
camera or world space; `world_normals` brings either to world space; conventions in `normalmaps`).
"""

from matspray.predictors.base import Predictor, predict_views
from matspray.predictors.encodings import BASECOLOR_ENCODINGS, decode_basecolor, encode_basecolor
from matspray.predictors.maps import (
    MATERIALS2D,
    MaterialMaps,
    maps_to_tensor,
    predicted_normal_maps,
    read_materials2d,
    read_predictor_info,
    without_normals,
    world_normals,
    write_materials2d,
)
from matspray.predictors.registry import (
    AUTO_PREDICTOR,
    NO_PREDICTOR,
    SPECS,
    PredictorOptions,
    make_predictor,
    options_for_dataset,
    resolve_predictor,
)

__all__ = [
    "AUTO_PREDICTOR",
    "BASECOLOR_ENCODINGS",
    "MATERIALS2D",
    "MaterialMaps",
    "NO_PREDICTOR",
    "Predictor",
    "PredictorOptions",
    "SPECS",
    "decode_basecolor",
    "encode_basecolor",
    "make_predictor",
    "maps_to_tensor",
    "options_for_dataset",
    "predict_views",
    "predicted_normal_maps",
    "resolve_predictor",
    "without_normals",
    "read_materials2d",
    "read_predictor_info",
    "world_normals",
    "write_materials2d",
]
