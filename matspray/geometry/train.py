"""3D Gaussian Splatting of one object: `train_geometry(scene, config, out_dir) -> Gaussians`.

Per step: one random training view; loss = photometric (L1 + D-SSIM on sRGB values, the RGBA photo
composited on a random background colour) + alpha L1 against the masks + a flattening regulariser +,
after `normal_from` of the run, consistency between the rendered normals (oriented shortest axes)
and the normals of the rendered depth and, with `predicted_normal_weight`, agreement of the rendered
normals (and, after `normal_from`, the depth's) with a 2D model's predicted normal maps. Adaptive density
control as in 3DGS; in a capture without masks, after `focus_from` of the run, only the Gaussians in the
object region grow (GeometryConfig's "object focus"). Writes, under out_dir: gaussians.ply, renders/ and
normals/ of the test views, metrics.json, region.json (the region focused on, if any), and checkpoint.pt
while it runs.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from tqdm import tqdm

from matspray.data.images import save_torch_atomic
from matspray.data.scene import Scene, View
from matspray.errors import DataError, RunError, SettingError, file_error
from matspray.files import write_json
from matspray.gaussians import Gaussians
from matspray.geometry.config import ADDED_LATER, GeometryConfig
from matspray.geometry.densify import DensityControl, load_stats_state, stats_state
from matspray.geometry.evaluate import evaluate_views
from matspray.geometry.init import initial_gaussians
from matspray.geometry.normals import consensus_normals, resize_normal_map
from matspray.geometry.optim import GaussianOptimizer, exponential_lr
from matspray.geometry.ply import read_ply, write_ply
from matspray.geometry.region import ObjectRegion, object_region
from matspray.geometry.step import ImageTerms, RunningStats, TrainingView, training_step

PLY_NAME, METRICS_NAME, CHECKPOINT_NAME = "gaussians.ply", "metrics.json", "checkpoint.pt"
REGION_NAME = "region.json"  # the object region a capture without masks focused on
# the loss and PSNR reach the host (a GPU synchronisation) only every this many steps, for the progress bar and
# the divergence check; on the CPU that costs nothing either way
SYNC_EVERY = 25


# ------------------------------------------------------------------------------------------ checkpoints
# written atomically, so an interrupted geometry run resumes where it stopped
CHECKPOINT_VERSION = 1


def save_checkpoint(path, config: GeometryConfig, iteration: int, state: dict, inputs: str | None = None) -> None:
    """`state`: tensors and plain values (optimizer, density statistics, random generator...); `inputs`: what the
    training was given (`train_geometry`)."""
    save_torch_atomic(
        {
            "version": CHECKPOINT_VERSION,
            "config": config.identity(),
            "inputs": inputs,
            "iteration": iteration,
            "state": state,
        },
        path,
    )


def load_checkpoint(path, config: GeometryConfig, inputs: str | None = None) -> tuple[int, dict] | None:
    """(iteration, state) of the checkpoint at `path`, None when there is none. Resuming a checkpoint of other
    inputs or settings would mix two runs: with `inputs` (`train_geometry`), one made for others is None too (its
    training is not this one's); without, one made with other settings is refused."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise file_error(
            path,
            f"is not a readable checkpoint ({type(exc).__name__}: {exc})",
            "delete it, or restart the geometry stage",
        ) from None
    if not isinstance(data, dict) or data.get("version") != CHECKPOINT_VERSION:
        raise file_error(
            path, "is not a matspray geometry checkpoint of this version", "delete it, or restart the geometry stage"
        )
    if inputs is not None:  # the inputs' identity covers the settings
        return (int(data["iteration"]), data["state"]) if data.get("inputs") == inputs else None
    saved = {**ADDED_LATER, **data["config"]}
    differences = sorted(k for k, v in config.to_dict().items() if saved.get(k) != v)
    if differences:
        shown = ", ".join(f"{k}: {saved.get(k)!r} -> {getattr(config, k)!r}" for k in differences[:4])
        raise RunError(
            f"{path}: was made with other geometry settings ({shown}); "
            "use another run folder, or delete it (`matspray geometry --restart` does) to discard the earlier training"
        )
    return int(data["iteration"]), data["state"]


def resumable(out_dir: Path, config: GeometryConfig, restart: bool, inputs: str | None) -> tuple[int, dict] | None:
    """The checkpoint in `out_dir` to resume (`load_checkpoint`), or None for a training from the start; then no file
    of an earlier training stays to be taken for this one's."""
    resumed = None if restart else load_checkpoint(out_dir / CHECKPOINT_NAME, config, inputs)
    if resumed is None:
        for name in (CHECKPOINT_NAME, PLY_NAME, METRICS_NAME, REGION_NAME):
            (out_dir / name).unlink(missing_ok=True)
    return resumed


def prepare_views(views: list[View], resolution: int) -> list[View]:
    """Views downscaled so that their longest side is `resolution` (never upscaled; 0 keeps them)."""
    out = []
    for view in views:
        factor = resolution / max(view.width, view.height) if resolution else 1.0
        out.append(view.scaled(factor) if factor < 1.0 - 1e-6 else view)
    return out


def scene_extent(views: list[View]) -> float:
    """3DGS's scene scale: 1.1 times the largest distance of a camera from the cameras' centroid."""
    centres = torch.stack([v.camera.center.double() for v in views])
    return 1.1 * float((centres - centres.mean(0)).norm(dim=-1).max().clamp_min(1e-6))


def learning_rates(config: GeometryConfig, extent: float) -> dict[str, float]:
    return {
        "means": config.lr_means * extent,
        "log_scales": config.lr_scales,
        "quats": config.lr_quats,
        "opacity_logits": config.lr_opacity,
        "sh_dc": config.lr_sh_dc,
        "sh_rest": config.lr_sh_rest,
    }


def train_geometry(
    scene: Scene,
    config: GeometryConfig,
    out_dir,
    *,
    device="cpu",
    restart: bool = False,
    progress: bool = True,
    cuda_graphs: bool = True,
    normal_targets: list | None = None,
    material_maps: list | None = None,
    object_bounds=None,
    focus_region: ObjectRegion | None = None,
    inputs: str | None = None,
) -> Gaussians:
    """Train Gaussians on `scene`'s training views on `device` and write the stage's artifacts into `out_dir`, with
    the backend of the enclosing `rendering_with` block (torch outside one). Resumes from out_dir/checkpoint.pt
    (settings must match; `restart` discards it; one made on another device resumes too); a finished run is not
    redone. Random draws come from a CPU generator: the same seed draws the same numbers on every device.
    `cuda_graphs`: on CUDA, the loss terms run as CUDA graphs (False: op by op, the same values).
    `normal_targets`: per training view, a predicted normal map [H, W, 3] in world space at the view's size (zero
    where there is none), which `config.predicted_normal_weight` pulls the normals towards (needed then).
    `material_maps`: per training view, its 2D maps [H, W, 5] (any size), whose edges
    `config.material_edge_threshold` splits Gaussians on (needed then). `object_bounds`: a capture without masks
    focuses on this region (`geometry.region.given_region`'s numbers) from `config.focus_from` on; `focus_region`:
    a region found before training (the photos' crop, `data.crop`) that it focuses on instead. `inputs`: what the
    training depends on (a pipeline's stage fingerprint); a checkpoint made for other inputs is trained over."""
    device = torch.device(device)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    train_views = [v.to(device) for v in prepare_views(scene.train, config.resolution)]  # moved once
    test_views = [v.to(device) for v in prepare_views(scene.test, config.resolution)]
    if not train_views:
        raise DataError(f"{scene.source}: no training views to fit geometry to")
    masked = all(v.alpha is not None for v in train_views)  # masks are used when every view has one
    config = config.for_scene(masked)
    check_inputs(config, normal_targets, material_maps, len(train_views))
    extent = scene_extent(train_views)
    generator = torch.Generator().manual_seed(config.seed)

    resumed = resumable(out_dir, config, restart, inputs)
    finished = resumed is not None and resumed[0] >= config.iterations
    if finished and (out_dir / PLY_NAME).exists() and (out_dir / METRICS_NAME).exists():
        return read_ply(out_dir / PLY_NAME)[0].to(device)
    start, order, optimizer, density, elapsed = training_state(
        scene, train_views, config, extent, generator, resumed, device
    )
    focus_at = focus_step(config)
    targets = training_targets(train_views, masked, config, normal_targets, material_maps, device)
    began = time.perf_counter() - elapsed
    steps = range(start, config.iterations)
    bar = tqdm(steps, initial=start, total=config.iterations, desc="geometry", disable=not progress, dynamic_ncols=True)
    running = RunningStats(device)
    image_terms = ImageTerms(graphs=cuda_graphs)
    for iteration in bar:
        if not order:
            order = torch.randperm(len(train_views), generator=generator, device="cpu").tolist()
        target = targets[order.pop()]
        means_lr = exponential_lr(
            iteration, config.iterations, config.lr_means * extent, config.lr_means_final * extent
        )
        optimizer.set_lr("means", means_lr)
        done = iteration + 1
        checkpoint_now = done % config.checkpoint_every == 0 or done == config.iterations
        # never checkpoint a state that diverged
        report = done % SYNC_EVERY == 0 or checkpoint_now
        event = training_step(optimizer, density, running, target, config, iteration, generator, image_terms, report)
        if report:
            count = len(optimizer.params["means"])
            bar.set_postfix(loss=f"{running.loss:.4f}", psnr=f"{running.psnr:.2f}", gaussians=count, refresh=False)
        if done == focus_at and density.region is None:
            focused = focus(optimizer, density, train_views, object_bounds, focus_region)
            event = ", ".join(e for e in (event, focused) if e)
        if event and progress:
            bar.write(f"iteration {iteration + 1}: {event}")
        if checkpoint_now:
            state = training_checkpoint(optimizer, density, generator, order, time.perf_counter() - began)
            save_checkpoint(out_dir / CHECKPOINT_NAME, config, done, state, inputs)
    bar.close()
    return write_result(out_dir, optimizer, density, train_views, test_views, config, time.perf_counter() - began)


def focus(optimizer, density, train_views, object_bounds, focus_region) -> str:
    """A capture without masks focuses its density control on the object region (`focus_region`, else the
    automatic rule or `object_bounds` on the Gaussians so far); returns what densification said."""
    g = optimizer.gaussians().detach()
    region = focus_region or object_region(g.means, g.opacities, [v.camera for v in train_views], object_bounds)
    return density.focus(optimizer, region)


def training_checkpoint(optimizer, density, generator, order: list, seconds: float) -> dict:
    """What a checkpoint keeps to resume training exactly: the optimizer, densification's statistics, the random
    generator, the views left in this epoch's order and the seconds trained."""
    return {
        "optimizer": optimizer.state_dict(),
        "density": stats_state(density),
        "generator": generator.get_state(),
        "order": order,
        "elapsed": seconds,
    }


def check_inputs(config: GeometryConfig, normal_targets: list | None, material_maps: list | None, views: int) -> None:
    """Refuses settings that need inputs not given, and inputs of the wrong length (`train_geometry`'s)."""
    if config.predicted_normal_weight > 0 and normal_targets is None:
        raise SettingError(
            "predicted_normal_weight",
            f"is {config.predicted_normal_weight}, but no predicted normal maps were given: train with "
            "`matspray run` and a predictor that gives normals, or set it to 0",
        )
    if config.material_edge_threshold > 0 and material_maps is None:
        raise SettingError(
            "material_edge_threshold",
            f"is {config.material_edge_threshold}, but no 2D material maps were given: train with `matspray run` and "
            "a predictor, or set it to 0",
        )
    for given, what in ((normal_targets, "normal maps"), (material_maps, "material maps")):
        if given is not None and len(given) != views:
            raise ValueError(f"{len(given)} {what} for {views} training views")


def training_state(scene: Scene, train_views: list[View], config, extent: float, generator, resumed, device):
    """(first iteration, the views left in this epoch's order, optimizer, density control, seconds trained so far):
    fresh Gaussians (drawn from `generator`), or the checkpoint `resumed` (iteration, state) restored."""
    if resumed is None:
        initial = initial_gaussians(
            scene,
            train_views,
            config.init_points,
            config.sh_degree,
            config.init_opacity,
            generator,
            config.init_scale,
            config.init,
        )
        optimizer = GaussianOptimizer(initial, learning_rates(config, extent))
        return 0, [], optimizer, DensityControl(config, extent, len(initial), device), 0.0
    start, state = resumed
    params = {name: t.to(device) for name, t in state["optimizer"]["params"].items()}
    optimizer = GaussianOptimizer(_empty_like(params), learning_rates(config, extent))
    optimizer.load_state_dict(dict(state["optimizer"], params=params))  # Adam moves its moments to the device
    density = DensityControl(config, extent, 0, device)
    load_stats_state(density, state["density"], device)
    generator.set_state(state["generator"])
    return start, state["order"], optimizer, density, state["elapsed"]


def training_targets(train_views, masked: bool, config, normal_targets, material_maps, device) -> list[TrainingView]:
    """What every step reads of each training view, with the predicted normals and material maps the settings use."""
    predicted = [None] * len(train_views)
    if config.predicted_normal_weight > 0:
        predicted = [resize_normal_map(n.to(device), v.height, v.width) for n, v in zip(normal_targets, train_views)]
    maps = [None] * len(train_views)
    if config.material_edge_threshold > 0:
        maps = [m.to(device) for m in material_maps]
    return [TrainingView.of(v, masked, n, m) for v, n, m in zip(train_views, predicted, maps)]


def write_result(out_dir: Path, optimizer, density, train_views, test_views, config, train_seconds: float) -> Gaussians:
    """The stage's artifacts: the Gaussians with their consensus normals (PLY), the focus region where there is one,
    and the held-out views' metrics."""
    gaussians = optimizer.gaussians().detach()
    normals = consensus_normals(gaussians, [v.camera for v in train_views])
    if density.region is not None:
        write_json(out_dir / REGION_NAME, density.region.to_json())
    write_ply(out_dir / PLY_NAME, gaussians, normals)
    metrics = evaluate_views(gaussians, test_views, config.sh_degree, out_dir)
    metrics.update(
        gaussians=len(gaussians), iterations=config.iterations, train_seconds=train_seconds, preset=config.preset
    )
    write_json(out_dir / METRICS_NAME, metrics)
    return gaussians


def focus_step(config: GeometryConfig) -> int | None:
    """The step after which a capture without masks focuses on its object: the first densification at or after
    `focus_from` of the iterations; None when off or when no densification follows it."""
    if config.focus_from <= 0:
        return None
    every = config.densify_every
    first = max(math.ceil(config.focus_from * config.iterations), config.densify_from + 1)
    step = math.ceil(first / every) * every
    return step if step < config.densify_until else None


def _empty_like(params: dict) -> Gaussians:
    return Gaussians(
        params["means"],
        params["log_scales"],
        params["quats"],
        params["opacity_logits"],
        torch.cat([params["sh_dc"], params["sh_rest"]], dim=1),
    )
