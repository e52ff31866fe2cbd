"""A simulated diffusion material predictor for benchmarks (`--predictor simulated`).

It turns the ground-truth maps of a `matspray synth` object into predictions with the failure modes
the paper describes for DiffusionRenderer, so that later stages can be measured against a known truth:

1. Lighting baked into base color. The model partly explains the photo's shading as albedo:
   base color is multiplied by the photo's diffuse shading ratio S = Y(photo) / Y(true base color),
   normalised to median 1 over the object, raised to an exponent (shadows darken it, highlights
   brighten it). How much lighting a window fails to remove depends on what that window saw (the
   paper: a batch "cannot recover the complete environment illumination"), so the exponent is drawn
   per batch, uniformly in `shading_strength` x [1 - `shading_spread`, 1 + `shading_spread`]. The
   shadows themselves sit at the same surface points in every view; only the batches' strength differs.
2. Tone mapping. Its training targets were tone mapped (supplement of the paper), so base color and
   roughness come out through a filmic view transform read back as sRGB: a sigmoid in log2 exposure
   (middle grey 0.18 kept, scene 1.0 -> display 0.8) that darkens bright base colors and compresses
   roughness [0.2, 1] into about [0.2, 0.6]. Metallic, mostly 0 or 1, is left alone.
3. Batches. Views are processed in dataset order in windows of `batch_size` (24 frames in
   DiffusionRenderer; 8 by default so a 40-view demo has several), and the model cannot see the whole
   illumination from one window: each batch gets its own exposure, white balance and colour shift,
   roughness offset, and a fraction of the batches a spurious partial metallic over the object. Views
   in a batch differ by a smaller jitter.
4. Blur: a Gaussian of `blur_fraction` of the image size, restricted to the object (latent-space
   models lose fine detail).
5. Per-view outliers (the `outliers` model): a fraction `cast_fraction` of the views gets a colour cast
   (per-channel gain exp(`cast_strength` * d), d a random unit direction with zero mean over RGB, so
   hue moves and brightness stays), a fraction `highlight_fraction` gets the photo's highlights baked
   into base colour (moved `highlight_amount` of the way to white where the photo is at least twice
   as bright, relative to the true base colour, as the object's median; from 1x to 2x it ramps up).
   Outlier views and metallic batches are spread evenly from a seeded start, so their count is the
   stated fraction for every seed.
6. Roughness collapse and single-view metallic (the `dr` model). The paper finds roughness hit hardest
   by the tone mapping (its values "collapse"): after the curve, each view's roughness moves
   `roughness_compression` of the way to its mean over the object, so the level stays the curve's and
   the batch's while the spread shrinks. DiffusionRenderer "often predicts partial metallicity in
   certain views": a fraction `metallic_view_fraction` of the views (spread evenly, like the outliers)
   gets a spurious metallic of its own, in `metallic_amplitude`, on top of any its batch has.
7. Normals (views with true normals, `{view}_normal.exr`; world space in and out). A latent diffusion
   model's normals are smooth and a little off, so in the view's camera frame each normal is turned by a
   smooth tilt field (independent Gaussian tilts about the camera's x and y axes at a `normal_tilt_cells`
   square grid of control points, `normal_tilt_deg` each, interpolated bicubically over the image, so the
   field is the same at any resolution), plus one tilt of the whole view (`normal_bias_deg`, and
   `normal_outlier_deg` more in the `outliers` model's colour-cast views), after a blur of
   `normal_blur_fraction` of the image size inside the object (lost detail). Pixels without a true normal
   keep none.
All effects apply to the object (alpha); background pixels keep their true values. The magnitudes of
each named error model are in `matspray.predictors.error_models`.

`severity` scales every effect (0 gives the ground truth exactly, 1 the default strength). Random
draws depend only on `seed`, which views are predicted (split folder and names) and positions, not on
severity, so severities form one family. The test views are one more set of frames: their batches draw
their own drifts and outliers, independent of the training views' (with draws shared by the two sets,
the 2D baseline of the test views would repeat the errors of a few training batches).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.data.images import srgb_to_linear
from matspray.data.scene import View
from matspray.predictors.base import Predictor
from matspray.predictors.error_models import SimulationConfig, model_name
from matspray.predictors.ground_truth import check_ground_truth, read_ground_truth
from matspray.predictors.maps import MaterialMaps
from matspray.predictors.normalmaps import camera_to_world, defined, renormalised, world_to_camera

LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance weights


@dataclass
class BatchDrift:
    """What one model window gets wrong (at the configured severity)."""

    exposure: float  # brightness gain
    white_balance: list[float]  # [3] per-channel gain
    color_shift: list[float]  # [3] additive, linear
    roughness_offset: float
    spurious_metallic: float  # 0 when this batch has none
    shading: float  # exponent of the baked-in shading ratio


# ------------------------------------------------------------------------------------------ effects
def luminance(rgb: Tensor) -> Tensor:  # [..., 3] -> [...]
    return rgb @ torch.tensor(LUMA, dtype=rgb.dtype, device=rgb.device)


def filmic_tone(x: Tensor) -> Tensor:  # [...] linear in [0, 1] -> [...] linear in [0, 1]
    """Scene value -> filmic display value (log2 sigmoid, 0.18 -> sRGB(0.18), 1.0 -> 0.8) -> decoded as sRGB."""
    width, pivot = 3.21, 0.249  # in stops; solve d(0.18) = 0.4613 (sRGB of 0.18) and d(1.0) = 0.8
    stops = torch.log2(x.clamp_min(1e-6) / 0.18)
    display = 0.5 + 0.5 * torch.tanh((stops - pivot) / width)
    return srgb_to_linear(display)


def shading_ratio(photo: Tensor, basecolor: Tensor, mask: Tensor) -> Tensor:
    """photo [H, W, 3] linear, basecolor [H, W, 3] linear, mask [H, W] bool -> S [H, W], median 1 on the mask."""
    albedo = luminance(basecolor)
    ratio = luminance(photo) / albedo.clamp_min(0.02)
    valid = mask & (albedo > 0.02)
    if not valid.any():
        return torch.ones_like(ratio)
    ratio = ratio / ratio[valid].median().clamp_min(1e-6)
    return torch.where(valid, ratio.clamp(1.0 / 8.0, 8.0), torch.ones_like(ratio))


def gaussian_kernel(sigma: float, dtype=torch.float32, device=None) -> Tensor:  # [2r + 1], sums to 1
    radius = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    return kernel / kernel.sum()


def blur_inside(x: Tensor, weight: Tensor, sigma: float) -> Tensor:
    """x [H, W, C], weight [H, W] in [0, 1] -> x blurred with a Gaussian, averaging only object pixels
    (normalised by the blurred weight), blended back by weight so the background keeps its values."""
    if sigma <= 0:
        return x
    kernel = gaussian_kernel(sigma, x.dtype, x.device)
    r = kernel.numel() // 2
    stack = torch.cat([x * weight[..., None], weight[..., None]], dim=-1).permute(2, 0, 1)[:, None]  # [C+1, 1, H, W]
    stack = F.conv2d(F.pad(stack, (r, r, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))
    stack = F.conv2d(F.pad(stack, (0, 0, r, r), mode="replicate"), kernel.view(1, 1, -1, 1))
    stack = stack[:, 0].permute(1, 2, 0)  # [H, W, C+1]
    blurred = stack[..., :-1] / stack[..., -1:].clamp_min(1e-6)
    return weight[..., None] * blurred + (1.0 - weight[..., None]) * x


@dataclass
class ViewOutlier:
    """What one view alone gets wrong (at the configured severity)."""

    cast: list[float]  # [3] per-channel gain; [1, 1, 1] when the view has no colour cast
    highlights: float  # how far base colour moves to white on a full highlight; 0 when none
    metallic: float = 0.0  # this view's own spurious partial metallic; 0 when none
    normal_deg: float = 0.0  # extra tilt (degrees) of this view's whole normal map; 0 when none


def evenly_spread(fraction: float, seed: int, stream: int, index: int) -> bool:
    """Whether item `index` is among a `fraction` of the items picked at even spacing from a start drawn
    from (seed, stream): any n consecutive items hold floor or ceil of fraction * n picks."""
    q = min(1.0, fraction)
    start = np.random.default_rng([int(seed), stream]).uniform()
    return q > 0 and (start + index * q) % 1.0 < q


def draw_view_outlier(config: SimulationConfig, index: int) -> ViewOutlier:
    """The outliers of the view at position `index` of the predicted list."""
    s = config.severity
    cast, normal_deg = [1.0, 1.0, 1.0], 0.0
    if evenly_spread(config.cast_fraction * s, config.seed, 4, index):
        direction = np.random.default_rng([int(config.seed), 5, index]).standard_normal(3)
        direction = direction - direction.mean()
        direction = direction / max(float(np.linalg.norm(direction)), 1e-9)
        cast = [float(v) for v in np.exp(config.cast_strength * s * direction)]
        normal_deg = config.normal_outlier_deg * s  # a view the model misread is misread in its normals too
    highlights = (
        min(1.0, config.highlight_amount * s)
        if evenly_spread(config.highlight_fraction * s, config.seed, 6, index)
        else 0.0
    )
    metallic = 0.0
    if evenly_spread(config.metallic_view_fraction * s, config.seed, 7, index):
        low, high = config.metallic_amplitude
        metallic = min(1.0, float(np.random.default_rng([int(config.seed), 8, index]).uniform(low, high)) * s)
    return ViewOutlier(cast=cast, highlights=highlights, metallic=metallic, normal_deg=normal_deg)


def compress_towards_mean(x: Tensor, mask: Tensor, amount: float) -> Tensor:  # [H, W], [H, W] bool -> [H, W]
    """x moved `amount` of the way to its mean over the mask: the spread shrinks by 1 - amount, the mean stays."""
    if amount <= 0 or not mask.any():
        return x
    return torch.lerp(x, x[mask].mean(), amount)


def combined_metallic(batch: float, view: float) -> float:
    """The spurious metallic of a view whose batch has `batch` and which has `view` of its own, both in [0, 1]:
    each moves the rest of the way to metal, so either alone is itself and together they stay <= 1."""
    return batch + view - batch * view  # = 1 - (1 - batch)(1 - view), exactly `batch` when view is 0


def highlight_weight(ratio: Tensor) -> Tensor:  # shading ratio S [H, W] (median 1) -> [H, W] in [0, 1]
    """0 up to the object's median brightness, 1 from twice the median, linear in between."""
    return (ratio - 1.0).clamp(0.0, 1.0)


def views_seed(seed: int, views: list[View]) -> int:
    """The seed of the draws for predicting `views`: `seed` and which views they are (split folder and
    name), so that the test views are predicted in batches of their own, with drifts and outliers drawn
    independently of the training views' (as a real model run on them would), while the same views
    always get the same errors."""
    ids = ",".join(f"{v.path.parent.name if v.path is not None else ''}/{v.name}" for v in views)
    return int(hashlib.sha1(f"{int(seed)}|{ids}".encode()).hexdigest()[:15], 16)


def draw_batch_drift(config: SimulationConfig, batch: int) -> BatchDrift:
    rng = np.random.default_rng([int(config.seed), 0, batch])
    s = config.severity
    normal = rng.standard_normal(8).clip(-3.0, 3.0)  # no freak outliers: severity alone sets the scale
    # (not left to chance, so that a 5-batch demo shows the failure mode for every seed)
    has_metal = evenly_spread(config.metallic_probability * s, config.seed, 2, batch)
    low, high = config.metallic_amplitude
    amplitude = rng.uniform(low, high) * s
    return BatchDrift(
        exposure=float(np.exp(config.exposure_sigma * s * normal[0])),
        white_balance=[float(v) for v in np.exp(config.white_balance_sigma * s * normal[1:4])],
        color_shift=[float(v) for v in config.color_shift_sigma * s * normal[4:7]],
        roughness_offset=float(config.roughness_offset_sigma * s * normal[7]),
        spurious_metallic=float(min(1.0, amplitude)) if has_metal else 0.0,
        # its own stream, so that adding it left every earlier draw as it was
        shading=float(
            config.shading_strength
            * s
            * (
                1.0
                + config.shading_spread * (2.0 * np.random.default_rng([int(config.seed), 3, batch]).uniform() - 1.0)
            )
        ),
    )


# ------------------------------------------------------------------------------------------ normals
def rotate_vectors(vectors: Tensor, rotvec: Tensor) -> Tensor:  # [..., 3], [..., 3] axis * angle (rad) -> [..., 3]
    """Each vector turned about its axis-angle rotation (Rodrigues' formula); a zero rotation leaves it exactly."""
    angle = rotvec.norm(dim=-1, keepdim=True)  # [..., 1]
    axis = rotvec / angle.clamp_min(1e-12)
    cos, sin = torch.cos(angle), torch.sin(angle)
    along = (axis * vectors).sum(-1, keepdim=True)
    return vectors * cos + torch.linalg.cross(axis, vectors, dim=-1) * sin + axis * along * (1.0 - cos)


def tilt_field(seed: int, index: int, cells: int, height: int, width: int, device=None) -> Tensor:  # -> [H, W, 2]
    """A smooth random field: independent standard normals at a cells x cells grid spanning the image,
    interpolated bicubically, drawn from (seed, index) alone, so every resolution gets the same field."""
    grid = np.random.default_rng([int(seed), 9, index]).standard_normal((2, cells, cells))
    field = F.interpolate(
        torch.as_tensor(grid, dtype=torch.float32, device=device)[None],
        size=(height, width),
        mode="bicubic",
        align_corners=True,
    )
    return field[0].permute(1, 2, 0)  # [H, W, 2]


def view_tilt(config: SimulationConfig, index: int, outlier: ViewOutlier | None) -> tuple[float, float]:
    """The tilt (degrees about the camera's x and y axes) of the whole normal map of view `index`."""
    draws = np.random.default_rng([int(config.seed), 10, index]).standard_normal(4)
    bias = draws[:2] * config.normal_bias_deg * config.severity
    extra = outlier.normal_deg if outlier is not None else 0.0
    direction = draws[2:] / max(float(np.linalg.norm(draws[2:])), 1e-9)  # the outlier's own direction
    return float(bias[0] + extra * direction[0]), float(bias[1] + extra * direction[1])


def simulate_normals(
    normals: Tensor,  # [H, W, 3] true world normals, unit or 0
    weight: Tensor,  # [H, W] object coverage in [0, 1]
    camera: Camera,
    config: SimulationConfig,
    index: int,
    outlier: ViewOutlier | None = None,
) -> Tensor:  # [H, W, 3] world normals, unit where the truth has a normal, 0 elsewhere
    """One view's predicted normals: blurred inside the object, then turned in the camera frame by the smooth
    tilt field and the view's own tilt. Severity 0 (or a model without normal errors) gives the truth."""
    s = config.severity
    tilt_x, tilt_y = view_tilt(config, index, outlier)
    sigma = config.normal_blur_fraction * s * max(normals.shape[:2])
    if config.normal_tilt_deg * s == 0 and tilt_x == 0 and tilt_y == 0 and sigma == 0:
        return normals.clone()
    has_normal = defined(normals)  # [H, W]
    inside = weight * has_normal.to(weight)  # pixels without a normal lend nothing to the blur
    blurred = renormalised(blur_inside(normals, inside, sigma))
    field = tilt_field(config.seed, index, int(config.normal_tilt_cells), *normals.shape[:2], normals.device)
    angles = field.to(normals) * config.normal_tilt_deg * s + normals.new_tensor([tilt_x, tilt_y])  # [H, W, 2] deg
    rotvec = torch.cat([torch.deg2rad(angles), torch.zeros_like(angles[..., :1])], dim=-1)  # about camera x, y
    turned = camera_to_world(rotate_vectors(world_to_camera(blurred, camera), rotvec), camera)
    mixed = renormalised(weight[..., None] * turned + (1.0 - weight[..., None]) * normals)  # edges lean to truth
    return torch.where(has_normal[..., None], mixed, torch.zeros_like(normals))


def simulate_view(
    truth: MaterialMaps,
    photo: Tensor,
    alpha: Tensor | None,
    drift: BatchDrift,
    config: SimulationConfig,
    index: int,
    outlier: ViewOutlier | None = None,
    camera: Camera | None = None,
) -> MaterialMaps:
    """One view's simulated prediction. truth: true maps (normals in world space, if any); photo [H, W, 3]
    linear; alpha [H, W] or None; index: the view's position in the predicted list (seeds its jitter);
    outlier: its own errors, if any; camera: the view's, needed when the truth has normals."""
    s = config.severity
    weight = torch.ones_like(truth.roughness) if alpha is None else alpha.to(truth.roughness).clamp(0.0, 1.0)
    mask = weight > 0.5
    jitter = np.random.default_rng([int(config.seed), 1, index]).standard_normal(2) * config.view_jitter_sigma * s
    tone = min(1.0, config.tone_strength * s)

    ratio = shading_ratio(photo.to(truth.basecolor), truth.basecolor, mask)  # [H, W]
    basecolor = (truth.basecolor * ratio[..., None] ** drift.shading).clamp(0.0, 1.0)
    if outlier is not None and outlier.highlights > 0:
        basecolor = torch.lerp(
            basecolor, torch.ones_like(basecolor), outlier.highlights * highlight_weight(ratio)[..., None]
        )
    basecolor = torch.lerp(basecolor, filmic_tone(basecolor), tone)
    gain = (
        torch.tensor(drift.white_balance, dtype=basecolor.dtype, device=basecolor.device)
        * drift.exposure
        * float(np.exp(jitter[0]))
    )
    if outlier is not None:
        gain = gain * torch.tensor(outlier.cast, dtype=basecolor.dtype, device=basecolor.device)
    basecolor = basecolor * gain + torch.tensor(drift.color_shift, dtype=basecolor.dtype, device=basecolor.device)

    roughness = torch.lerp(truth.roughness, filmic_tone(truth.roughness), tone)
    roughness = compress_towards_mean(roughness, mask, min(1.0, config.roughness_compression * s))
    roughness = roughness + drift.roughness_offset + float(jitter[1])
    spurious = combined_metallic(drift.spurious_metallic, outlier.metallic if outlier is not None else 0.0)
    metallic = truth.metallic + spurious * (1.0 - truth.metallic) * weight

    maps = torch.cat([basecolor, roughness[..., None], metallic[..., None]], dim=-1)
    maps = blur_inside(maps, weight, config.blur_fraction * s * max(maps.shape[:2])).clamp(0.0, 1.0)
    truth_stack = torch.cat([truth.basecolor, truth.roughness[..., None], truth.metallic[..., None]], dim=-1)
    maps = weight[..., None] * maps + (1.0 - weight[..., None]) * truth_stack  # the background keeps its true values
    normals = None
    if truth.normals is not None:
        if camera is None:
            raise ValueError("simulate_view needs the view's camera to predict its normals")
        if truth.normal_space != "world":
            raise ValueError(f"simulate_view takes world-space true normals, got '{truth.normal_space}'")
        normals = simulate_normals(truth.normals, weight, camera, config, index, outlier)
    return MaterialMaps(
        maps[..., :3].contiguous(),
        maps[..., 3].contiguous(),
        maps[..., 4].contiguous(),
        normals=normals,
        normal_space="world",
    )


class SimulatedPredictor(Predictor):
    """Ground truth degraded like a video diffusion model's output (benchmarks only)."""

    name = "simulated"
    simulated = True
    benchmark_only = True

    def __init__(self, config: SimulationConfig | None = None):
        self.config = config or SimulationConfig()
        self.batches: list[dict] = []  # what each batch got, filled by predict (for predictor.json)
        self.outliers: list[dict] = []  # the views with outliers of their own, filled by predict

    def describe(self) -> dict:
        note = (
            f"SIMULATED from ground truth for benchmarks (error model '{model_name(self.config)}'); "
            "not a real prediction"
        )
        config = asdict(self.config)
        config["metallic_amplitude"] = list(self.config.metallic_amplitude)
        return dict(
            super().describe(),
            note=note,
            error_model=model_name(self.config),
            settings=config,
            batches=self.batches,
            outliers=self.outliers,
        )

    def predict(self, views: list[View]) -> dict[str, MaterialMaps]:
        check_ground_truth(views)
        out, self.batches, self.outliers = {}, [], []
        draws = replace(self.config, seed=views_seed(self.config.seed, views))
        size = int(self.config.batch_size)
        with tqdm(
            total=len(views), desc="simulated predictions", unit="view", disable=None
        ) as bar:  # no bar where output is not a terminal
            for batch, start in enumerate(range(0, len(views), size)):
                drift = draw_batch_drift(draws, batch)
                members = views[start : start + size]
                self.batches.append(dict(asdict(drift), views=[v.name for v in members]))
                for offset, view in enumerate(members):
                    truth = read_ground_truth(view)
                    outlier = draw_view_outlier(draws, start + offset)
                    if outlier != ViewOutlier([1.0, 1.0, 1.0], 0.0):
                        self.outliers.append(dict(asdict(outlier), view=view.name))
                    out[view.name] = simulate_view(
                        truth, view.image, view.alpha, drift, draws, start + offset, outlier, view.camera
                    )
                    bar.update(1)
        return out
