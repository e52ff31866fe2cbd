"""Marigold-IID (appearance model) through diffusers' `MarigoldIntrinsicsPipeline` (`--predictor marigold`).

The appearance model predicts two targets: `albedo` (3 channels, sRGB space) and `material`, a stack
of `roughness` (R) and `metallicity` (G), both linear; `target_properties` in the pipeline's config
names them, and is checked here. Weights come from a local folder (`save_pretrained` layout), or from
the Hugging Face hub by id when the network allows. With `ensemble_size` >= 3 the pipeline's
uncertainty becomes the maps' confidence (1 - mean uncertainty).

With `normals_weights`, Marigold's normals model (diffusers' `MarigoldNormalsPipeline`) runs beside it on the
same photos and its output becomes the maps' normals, in camera space. Marigold's normals are unit vectors
in a camera frame with x right, y up and z towards the viewer; they are turned into MatSpray's (OpenCV: x
right, y down, z forward) by negating y and z, and set to (0, 0, 0) off the object where the view has a mask.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data.images import linear_to_srgb, srgb_to_linear
from matspray.data.scene import View
from matspray.device import resolve_device
from matspray.errors import ConfigError, DataError, SettingError, file_error
from matspray.predictors.base import Predictor
from matspray.predictors.encodings import check_encoding, decode_basecolor
from matspray.predictors.maps import MaterialMaps
from matspray.predictors.normalmaps import from_opengl_camera, renormalised

DEFAULT_WEIGHTS = "prs-eth/marigold-iid-appearance-v1-1"
PIPELINE_CLASS = "MarigoldIntrinsicsPipeline"
DOWNLOAD_HINT = (
    f"on a machine with network access run `hf download {DEFAULT_WEIGHTS} --local-dir marigold-iid-appearance` "
    "(pip install huggingface_hub), copy that folder here and pass --weights marigold-iid-appearance"
)
NORMALS_WEIGHTS = "prs-eth/marigold-normals-v1-1"  # the normals model to name in `normals_weights`
NORMALS_CLASS = "MarigoldNormalsPipeline"
NORMALS_HINT = (
    f"on a machine with network access run `hf download {NORMALS_WEIGHTS} --local-dir marigold-normals` "
    "(pip install huggingface_hub), copy that folder here and pass --normals-weights marigold-normals"
)


@dataclass
class MarigoldConfig:
    weights: str = DEFAULT_WEIGHTS  # local pipeline folder, or a hub id
    device: str = "auto"  # auto (CUDA when available), cpu, cuda, cuda:N
    batch_size: int = 4  # views per pipeline call
    steps: int | None = None  # denoising steps; None = the model's default
    ensemble_size: int = 1  # predictions averaged per view; >= 3 also gives a confidence map
    processing_resolution: int | None = None  # None = the model's default; 0 = the image's own
    seed: int = 0
    basecolor_encoding: str | None = None  # None = as the model's config says (sRGB for the appearance model)
    normals_weights: str | None = None  # MarigoldNormalsPipeline folder or hub id; None = no normals

    def __post_init__(self) -> None:
        for name in ("batch_size", "ensemble_size"):
            if int(getattr(self, name)) < 1:
                raise SettingError(name, f"must be >= 1, got {getattr(self, name)}")
        if self.steps is not None and int(self.steps) < 1:
            raise SettingError("steps", f"must be >= 1, got {self.steps}")
        if self.basecolor_encoding is not None:
            self.basecolor_encoding = check_encoding(self.basecolor_encoding)


def load_pipeline(weights: str):
    """diffusers' MarigoldIntrinsicsPipeline from a local folder or a hub id, with clear errors."""
    return _load(weights, PIPELINE_CLASS, "the Marigold-IID appearance model", DOWNLOAD_HINT)


def load_normals_pipeline(weights: str):
    """diffusers' MarigoldNormalsPipeline from a local folder or a hub id, with clear errors."""
    return _load(weights, NORMALS_CLASS, "Marigold's normals model", NORMALS_HINT)


def _load(weights: str, class_name: str, model: str, hint: str):
    try:
        import diffusers

        pipeline_class = getattr(diffusers, class_name)
    except (ImportError, AttributeError):  # no diffusers, or one too old for this pipeline
        raise ConfigError(
            "the marigold predictor needs diffusers and transformers: pip install 'matspray[marigold]'"
        ) from None
    path = Path(weights).expanduser()
    if path.exists():
        index = path / "model_index.json"
        if not index.is_file():
            raise file_error(path, "is not a diffusers pipeline folder (no model_index.json)", hint)
        try:
            found = json.loads(index.read_text()).get("_class_name")
        except (json.JSONDecodeError, OSError, UnicodeDecodeError) as exc:
            raise file_error(index, f"cannot read: {exc}") from None
        if found != class_name:
            raise file_error(index, f"holds a {found}, not a {class_name}", f"use {model}: {hint}")
        try:
            return pipeline_class.from_pretrained(str(path), local_files_only=True)
        except (OSError, ValueError, KeyError, RuntimeError) as exc:
            raise file_error(path, f"cannot load the pipeline: {exc}") from None
    if weights.count("/") != 1 or weights.startswith((".", "/", "~")):
        raise file_error(path, "does not exist", f"the weights setting takes a pipeline folder or a hub id; {hint}")
    try:
        return pipeline_class.from_pretrained(weights)
    except Exception as exc:  # no network, unknown repo, interrupted download: all end the same way
        raise ConfigError(
            f"cannot get Marigold weights '{weights}' from the Hugging Face hub ({type(exc).__name__}); {hint}"
        ) from None


def target_layout(properties: dict | None) -> dict[str, tuple[int, int | None, str]]:
    """Where albedo, roughness and metallicity are in the output: name -> (target index, channel or None
    for all three, prediction space). ConfigError when the model does not predict all three."""
    properties = properties or {}
    names = properties.get("target_names") or []
    found = {}
    for index, target in enumerate(names):
        entry = properties.get(target, {})
        if entry.get("prediction_space") == "stack":
            for channel, sub in enumerate(entry.get("sub_target_names") or []):
                if sub:
                    found[sub] = (index, channel, properties.get(sub, {}).get("prediction_space", "linear"))
        else:
            found[target] = (index, None, entry.get("prediction_space", "srgb"))
    missing = [n for n in ("albedo", "roughness", "metallicity") if n not in found]
    if missing:
        raise ConfigError(
            f"this Marigold model predicts {', '.join(sorted(found)) or 'nothing known'} but not {', '.join(missing)}; "
            f"the material predictor needs the appearance model ({DEFAULT_WEIGHTS})"
        )
    return found


def photo_batch(views: list[View]) -> Tensor:  # -> [B, 3, H, W] sRGB-encoded in [0, 1], object over black
    images = []
    for view in views:
        rgb = view.image if view.alpha is None else view.image * view.alpha[..., None]
        images.append(linear_to_srgb(rgb).permute(2, 0, 1))
    return torch.stack(images)


class MarigoldPredictor(Predictor):
    name = "marigold"

    def __init__(self, config: MarigoldConfig | None = None, notify: Callable[[str], None] = print):
        self.config = config or MarigoldConfig()
        self.device = resolve_device(self.config.device)
        self.pipe = load_pipeline(self.config.weights).to(self.device)
        self.pipe.set_progress_bar_config(disable=True)
        self.targets = target_layout(self.pipe.target_properties)
        self.normals_pipe = None
        if self.config.normals_weights is not None:
            self.normals_pipe = load_normals_pipeline(self.config.normals_weights).to(self.device)
            self.normals_pipe.set_progress_bar_config(disable=True)
        self.notify = notify

    def describe(self) -> dict:
        info = dict(
            super().describe(),
            settings=asdict(self.config),
            device=str(self.device),
            targets=list(self.pipe.target_properties["target_names"]),
        )
        if self.normals_pipe is not None:
            info["normals"] = "marigold normals, camera space (OpenCV axes)"
        return info

    def _call(self, pipe, name: str, views: list[View], first: int, **extra):
        """One diffusers Marigold pipeline on `views` (the batch starting at view `first`, which seeds it)."""
        c = self.config
        try:
            return pipe(
                photo_batch(views).to(self.device, pipe.dtype),
                num_inference_steps=c.steps,
                ensemble_size=c.ensemble_size,
                processing_resolution=c.processing_resolution,
                batch_size=len(views),
                generator=torch.Generator().manual_seed(int(c.seed) + first),
                output_type="pt",
                **extra,
            )
        except ValueError as exc:  # diffusers' input checks
            raise ConfigError(f"{name} rejected the settings: {exc}") from None

    def _normals(self, views: list[View], first: int) -> list[Tensor]:  # -> N x [H, W, 3] camera space, ours
        """The normals model's prediction for `views`, turned into MatSpray's camera axes, 0 off the object."""
        output = self._call(self.normals_pipe, "Marigold's normals model", views, first)
        normals = renormalised(from_opengl_camera(output.prediction.float().cpu().permute(0, 2, 3, 1)))  # [N, H, W, 3]
        out = []
        for view, n in zip(views, normals):
            if view.alpha is not None:  # the masked photo's black background is no surface: no normal there
                n = torch.where(view.alpha.cpu()[..., None] > 0, n, torch.zeros_like(n))
            out.append(n.contiguous())
        return out

    def _channel(self, prediction: Tensor, name: str) -> Tensor:  # [N, T, 3, H, W] -> [N, H, W(, 3)]
        index, channel, _ = self.targets[name]
        values = prediction[:, index]  # [N, 3, H, W]
        return values.permute(0, 2, 3, 1) if channel is None else values[:, channel]

    def _run(self, views: list[View], first: int) -> list[MaterialMaps]:
        c = self.config
        with_confidence = c.ensemble_size >= 3
        output = self._call(self.pipe, "Marigold", views, first, output_uncertainty=with_confidence)
        n, t = len(views), len(self.pipe.target_properties["target_names"])
        prediction = output.prediction.float().cpu().reshape(n, t, 3, *output.prediction.shape[-2:])
        albedo = self._channel(prediction, "albedo")
        space = self.targets["albedo"][2]
        encoding = c.basecolor_encoding or ("linear" if space == "linear" else "srgb")
        basecolor = decode_basecolor(albedo, encoding)
        roughness, metallic = self._channel(prediction, "roughness"), self._channel(prediction, "metallicity")
        if self.targets["roughness"][2] == "srgb":
            roughness = srgb_to_linear(roughness)
        if self.targets["metallicity"][2] == "srgb":
            metallic = srgb_to_linear(metallic)
        confidence = [None] * n
        if with_confidence:
            uncertainty = output.uncertainty.float().cpu().reshape(n, t, 3, *output.uncertainty.shape[-2:])
            confidence = list((1.0 - uncertainty.mean(dim=(1, 2))).clamp(0.0, 1.0))
        normals = self._normals(views, first) if self.normals_pipe is not None else [None] * n
        return [
            MaterialMaps(
                basecolor[i].clamp(0, 1),
                roughness[i].clamp(0, 1),
                metallic[i].clamp(0, 1),
                confidence[i],
                normals=normals[i],
                normal_space="camera",
            )
            for i in range(n)
        ]

    def predict(self, views: list[View]) -> dict[str, MaterialMaps]:
        sizes = {(v.height, v.width) for v in views}
        if len(sizes) > 1:
            raise DataError(f"Marigold needs views of one size per run, got {sorted(sizes)}")
        out = {}
        size = int(self.config.batch_size)
        with torch.no_grad(), tqdm(total=len(views), desc=f"marigold ({self.device})", unit="view") as bar:
            for start in range(0, len(views), size):
                batch = views[start : start + size]
                for view, maps in zip(batch, self._run(batch, start)):
                    out[view.name] = maps
                bar.update(len(batch))
        return out
