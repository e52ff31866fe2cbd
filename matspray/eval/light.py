"""How good an estimated environment light is, against the true training light of a synthetic object.

tv_ratio                total variation of the estimate's log radiance over the truth's, the truth
                        first area-resampled to the estimate's size (1: as smooth as the real light;
                        a noisy estimate is several times rougher)
irradiance_correlation  Pearson's r of the two lights' order-2 spherical-harmonic irradiance (what
                        diffuse shading sees; 1: the same up to a scale)
"""

from __future__ import annotations

from pathlib import Path

from torch import Tensor

from matspray.data.formats.blender import read_scene_json
from matspray.errors import file_error
from matspray.render.shade.envmap import MIN_RADIANCE, EnvironmentMap, downsample_latlong
from matspray.render.shade.latlong import irradiance_correlation, total_variation


def light_figures(estimate: Tensor, truth: Tensor) -> dict:  # [h, 2h, 3], [H, 2H, 3] linear radiance, H >= h
    truth_at_size = downsample_latlong(truth.double(), estimate.shape[0])
    tv_estimate = float(total_variation(estimate.double().clamp_min(MIN_RADIANCE).log()))
    tv_truth = float(total_variation(truth_at_size.clamp_min(MIN_RADIANCE).log()))
    return {
        "tv_estimate": tv_estimate,
        "tv_truth": tv_truth,
        "tv_ratio": tv_estimate / max(tv_truth, 1e-12),
        "irradiance_correlation": irradiance_correlation(estimate, truth),
    }


def training_light_path(data) -> Path | None:
    """The file of the training light of a `matspray synth` object (named in its scene.json),
    or None for other datasets."""
    lights = (read_scene_json(Path(data)) or {}).get("lights")
    name = lights.get("train") if isinstance(lights, dict) else None
    if not isinstance(name, str):
        return None
    path = Path(data) / "envmaps" / f"{name}.exr"
    if not path.exists():
        raise file_error(path, f"the training light '{name}' named in scene.json is missing")
    return path


def training_light(data) -> tuple[str, Tensor] | None:
    """The training light of a `matspray synth` object (name, [H, 2H, 3]), or None for other datasets."""
    path = training_light_path(data)
    return None if path is None else (path.stem, EnvironmentMap.from_file(path).map.detach())
