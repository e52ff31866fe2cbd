"""2D-to-3D material lifting (paper section 3.2, eq. 1-3).

For every training view, rays on a k x k sub-pixel grid are traced through the Gaussians with the
3DGRT response (`matspray.render.rays.contributions`). Every Gaussian a ray hits while it is still visible
(the ray's transmittance before the hit is at least `visibility_threshold`) receives the material of
the pixel the ray belongs to. Per Gaussian and view the median of what it received is kept (eq. 3);
samples from one pixel carry one value, so the median is taken over pixels weighted by how many of
the pixel's samples hit the Gaussian. Gaussians hit in no view are removed.

The footprint the median runs over is the Gaussian's core: the rays passing within `footprint_sigmas`
standard deviations of its centre (the paper's released code intersects rays with the 1-sigma
ellipsoid). A ray reaches alpha_max >= 1/255 out to ~3.3 sigma, and that ring holds most of the pixels
a Gaussian touches, so a median over all of them mostly reads the neighbours' materials and blurs thin
features. A Gaussian whose core no ray met in a view (smaller than the sample spacing, or its core
hidden) takes the median of all its hits there, so no Gaussian is missed for being small; which views
see a Gaussian, and which Gaussians are kept, do not depend on the footprint.

A view counts as seeing a Gaussian (`seen`, the mask the Neural Merger and Proj. Average use) when the
Gaussian receives at least `min_support` times the samples it receives in the view that sees it best.
Views with fewer hits are glimpses (nearly occluded, grazing, or the edge of a footprint that lies
on another surface); on the demo object their medians disagree with the other views more than
twice as often as the best-seen views' (`python -m benchmarks.lift_support`). Every hit view keeps
its median in `values` and its sample count in `hits`.

`save_lift` / `load_lift`: the stage's file (RUN/lift/projected.pt), checked against the run when read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.data.images import save_torch_atomic
from matspray.errors import MatsprayError, SettingError, check_unit_interval, file_error
from matspray.gaussians import Gaussians
from matspray.geometry.ply import vertex_count
from matspray.material import zeros as material_zeros
from matspray.render.backend import active_backend, note_render
from matspray.render.rays.contributions import iter_contributions
from matspray.render.settings import RasterSettings
from matspray.rundir import RunDir, read_json, stage_folder, stage_hint, to_plain
from matspray.settings import setting

QUANTISATION = 65535  # material values are 8/16-bit PNGs: medians are exact at this resolution
DEFAULT_BAND_SAMPLES = 1 << 21  # iter_contributions' default
BYTES_PER_CANDIDATE = 160  # the float64 temporaries of one (Gaussian, ray) candidate in the tracer, with margin


@dataclass(frozen=True)
class LiftConfig:
    samples_per_side: int = setting(4, "k: k x k rays per pixel (the paper uses 16)")
    visibility_threshold: float = setting(
        0.0,
        "a hit counts while transmittance before it is >= this (0, every hit: the paper, and our default)",
    )
    falloff: float = setting(1.0, "lambda of eq. (2)")
    mask_threshold: float = setting(0.5, "pixels whose object mask is below this give nothing")
    min_support: float = setting(
        0.5,
        "a view sees a Gaussian when it gets >= this share of its best view's hits (0: any hit)",
    )
    footprint_sigmas: float | None = setting(
        1.0,
        "a ray hits a Gaussian when it passes within this many standard deviations of its centre (the paper's"
        " released code intersects the 1-sigma ellipsoid); None: wherever alpha_max >= min_alpha (~3.3 sigma)",
    )

    def __post_init__(self):
        check_unit_interval(self, "min_support", "visibility_threshold", "mask_threshold")
        if not 1 <= self.samples_per_side <= 32:
            raise SettingError("samples_per_side", f"must be in 1..32, got {self.samples_per_side}")
        if self.footprint_sigmas is not None and not self.footprint_sigmas > 0:
            raise SettingError("footprint_sigmas", f"must be > 0 (or None: every hit), got {self.footprint_sigmas}")
        if not self.falloff > 0:
            raise SettingError("falloff", f"must be > 0, got {self.falloff}")


@dataclass
class LiftResult:
    values: Tensor  # [N, V, 5] per-view medians (base color rgb linear, roughness, metallic); 0 where not hit
    seen: Tensor  # [N, V] bool: the view sees the Gaussian well enough to count (`LiftConfig.min_support`)
    kept: Tensor  # [N_in] bool: which input Gaussians were hit in at least one view (the N kept ones)
    view_names: list[str]
    stats: dict = field(default_factory=dict)
    hits: Tensor | None = None  # [N, V] int: (pixel, sample) hits each Gaussian received in each view


def supported_views(hits: Tensor, min_support: float) -> Tensor:  # [N, V] counts -> [N, V] bool
    """Views whose hits reach `min_support` times the Gaussian's best view (a hit view always counts at 0)."""
    best = hits.amax(dim=1, keepdim=True)
    return (hits > 0) & (hits >= min_support * best)


def weighted_median(group_ids: Tensor, values: Tensor, weights: Tensor, n_groups: int) -> tuple[Tensor, Tensor]:
    """Lower weighted median of `values` [M] within each group.

    group_ids [M] in [0, n_groups), values [M] in [0, 1], weights [M] >= 0 (integer counts or reals; an entry of
    weight 0 is never the median). Returns medians [n_groups] (0 for empty groups) and has_value [n_groups] bool. The
    median is the first value (in sorted order) at which the cumulative weight reaches half the group's total.
    """
    medians, has_value = weighted_medians(group_ids, values[:, None], weights, n_groups)
    return medians[:, 0], has_value


def weighted_medians(group_ids: Tensor, values: Tensor, weights: Tensor, n_groups: int) -> tuple[Tensor, Tensor]:
    """`weighted_median` of every channel of `values` [M, C] at once: medians [n_groups, C], has_value [n_groups].

    One sort of all channels' entries, by (channel, group, quantised value), and no host read: the one entry per
    channel and group where the cumulative weight crosses half the group's total is summed into its place (every
    other entry adds 0), so the result needs no selection whose size the host must learn."""
    groups = group_ids.long()
    count, channels = values.shape
    quantised = torch.round(values.clamp(0, 1) * QUANTISATION).long()  # [M, C]
    slots = torch.arange(channels, device=values.device) * n_groups + groups[:, None]  # [M, C] (channel, group)
    order = torch.argsort((slots * (QUANTISATION + 1) + quantised).reshape(-1))  # [M C] one flat sort
    slots_sorted = slots.reshape(-1)[order]
    weights_sorted = weights.double()[:, None].expand(count, channels).reshape(-1)[order]
    totals = torch.zeros(n_groups, dtype=torch.float64, device=values.device).index_add_(0, groups, weights.double())
    slot_totals = totals.repeat(channels)  # [C n_groups]
    before_slot = torch.cumsum(slot_totals, 0) - slot_totals  # weight of all earlier (channel, group) slots
    cumulative = torch.cumsum(weights_sorted, 0) - before_slot[slots_sorted]  # running total within the slot
    half = slot_totals[slots_sorted] / 2
    crossing = (cumulative >= half) & (cumulative - weights_sorted < half)  # one entry per slot
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    picked = torch.where(crossing, values.reshape(-1)[order], zero)
    medians = torch.zeros(channels * n_groups, dtype=values.dtype, device=values.device)
    medians = medians.scatter_add_(0, slots_sorted, picked).view(channels, n_groups).T  # [n_groups, C]
    return medians, totals > 0


def footprint_alpha(opacities: Tensor, config: LiftConfig, max_alpha: float) -> Tensor | None:  # [N] -> [N]
    """The alpha_max a ray reaches where it passes `config.footprint_sigmas` standard deviations from a
    Gaussian's centre (eq. 2: alpha_max = opacity exp(-lambda d^2 / 2)), capped at `max_alpha`, the
    clamp the hits' alphas went through; None when the footprint is the whole extent a ray can hit."""
    if config.footprint_sigmas is None:
        return None
    return (opacities * math.exp(-0.5 * config.falloff * config.footprint_sigmas**2)).clamp(max=max_alpha)


def traced_entries(
    gaussians: Gaussians,
    camera: Camera,
    mask: Tensor | None,
    config: LiftConfig,
    settings: RasterSettings,
    core_alpha: Tensor | None,
) -> tuple[Tensor, Tensor]:
    """What a view gives the Gaussians, by the torch tracer: one key [M] per (Gaussian, pixel, inside the core or
    not), (Gaussian * pixels + pixel) * 2 + inside, and how many of the pixel's rays hit it there [M], counting hits
    that are still visible (`visibility_threshold`) on pixels of the object."""
    n_pixels = camera.width * camera.height
    dropped = len(gaussians) * n_pixels * 2  # a key above every entry's: hits that give nothing
    flat_mask = None if mask is None else mask.reshape(-1)
    pair_keys, pair_counts = [], []
    for band in iter_contributions(
        gaussians,
        camera,
        config.samples_per_side,
        falloff=config.falloff,
        settings=settings,
        max_samples=band_samples(gaussians.means.device),
    ):  # whole rays, a band of rows at a time
        # every hit keeps its place and the ones that give nothing get the key `dropped`: no selection whose size the
        # host must learn before the one count of distinct keys (on a GPU each such read waits for the queue)
        transmittance = band.weights / band.alphas.clamp_min(1e-12)  # in front of the hit
        gives = transmittance >= config.visibility_threshold
        if flat_mask is not None:
            gives = gives & (flat_mask[band.pixel_ids] >= config.mask_threshold)
        key = band.gaussian_ids.long() * n_pixels + band.pixel_ids.long()
        if core_alpha is not None:  # inside the core, or not
            key = key * 2 + (band.alphas >= core_alpha[band.gaussian_ids]).long()
        else:
            key = key * 2 + 1
        keys, counts = torch.unique(torch.where(gives, key, dropped), return_counts=True)
        pair_keys.append(keys)
        pair_counts.append(counts)
    # bands hold disjoint pixels, so no entry appears twice
    device = gaussians.means.device
    keys = torch.cat(pair_keys) if pair_keys else torch.zeros(0, dtype=torch.long, device=device)
    counts = torch.cat(pair_counts) if pair_counts else torch.zeros(0, dtype=torch.long, device=device)
    real = keys < dropped
    return keys[real], counts[real]


def band_samples(device: torch.device) -> int:
    """How many (Gaussian, ray) candidates the torch tracer evaluates at once on `device`: on a GPU as many as an
    eighth of its free memory holds, since each band is a few dozen kernel launches and host reads (bands split the
    work only where it must, into whole rays, so the hits are the same whatever the size); on the CPU the tracer's
    default, which keeps memory small."""
    if device.type != "cuda":
        return DEFAULT_BAND_SAMPLES
    free, _ = torch.cuda.mem_get_info(device)
    return int(min(max(free // 8 // BYTES_PER_CANDIDATE, DEFAULT_BAND_SAMPLES), 1 << 30))


def compiled_entries(
    gaussians: Gaussians,
    camera: Camera,
    mask: Tensor | None,
    config: LiftConfig,
    settings: RasterSettings,
    core_alpha: Tensor | None,
) -> tuple[Tensor, Tensor]:
    """`traced_entries` by numba's tile loops (`matspray.render.numba.rays`; CPU): the same entries, in another
    order."""
    from matspray.render.numba.rays import trace_view  # numba loads where it traces

    on_object = (
        torch.ones(camera.height * camera.width, dtype=torch.bool)
        if mask is None
        else mask.reshape(-1).cpu() >= config.mask_threshold
    )
    # without a footprint every hit is inside the core: an edge alpha of 0 says so
    core = torch.zeros(len(gaussians)) if core_alpha is None else core_alpha
    return trace_view(
        gaussians, camera, on_object, config.samples_per_side, core, config.falloff, settings,
        config.visibility_threshold,
    )  # fmt: skip


def lift_view(
    gaussians: Gaussians, camera: Camera, materials: Tensor, mask: Tensor | None, config: LiftConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """Lift one view's material maps [H, W, 5] (mask [H, W] or None) onto the Gaussians.

    Returns medians [N, 5], seen [N] bool, and hits [N] (number of (pixel, sample) hits received).
    """
    n = len(gaussians)
    n_pixels = camera.width * camera.height
    settings = RasterSettings()
    core_alpha = footprint_alpha(gaussians.opacities.detach(), config, settings.max_alpha)  # [N] or None
    # lifting traces rays with our own code whatever the rasterizer: compiled where the run renders with numba, else
    # torch on the Gaussians' device
    compiled = active_backend() == "numba"
    note_render("rays-numba" if compiled else "rays")
    entries = compiled_entries if compiled else traced_entries
    keys, counts = entries(gaussians, camera, mask, config, settings, core_alpha)
    keys, counts = keys.to(materials.device), counts.to(materials.device)
    in_core, pairs = (keys % 2).bool(), keys // 2
    pair_gaussians, pair_pixels = pairs // n_pixels, pairs % n_pixels
    received = torch.zeros(n, dtype=torch.long, device=materials.device).index_add_(0, pair_gaussians, counts)
    # the median runs over the core's pixels; a Gaussian whose core no ray met (tiny, or its core hidden) uses all
    # its hits
    core_hits = torch.zeros(n, dtype=torch.long, device=materials.device).index_add_(0, pair_gaussians, in_core.long())
    # one host read: the median sorts only the entries it uses (the core's are a small share of a Gaussian's hits)
    chosen = torch.nonzero(in_core | (core_hits == 0)[pair_gaussians]).squeeze(1)
    pair_gaussians, pair_pixels = pair_gaussians.index_select(0, chosen), pair_pixels.index_select(0, chosen)
    flat = materials.reshape(-1, materials.shape[-1])[pair_pixels]  # [P, 5]
    medians, _ = weighted_medians(pair_gaussians, flat, counts.index_select(0, chosen), n)  # [N, 5]
    return medians, received > 0, received  # every Gaussian with a hit keeps at least one entry


def lift(
    gaussians: Gaussians,
    cameras: list[Camera],
    materials: list[Tensor],
    masks: list[Tensor | None],
    view_names: list[str],
    config: LiftConfig | None = None,
    progress: bool = True,
) -> LiftResult:
    """Lift every view's maps ([H, W, 5] each) and drop the Gaussians no view saw."""
    config = config or LiftConfig()
    n, v = len(gaussians), len(cameras)
    values = material_zeros(n, v, device=gaussians.device)
    hits = torch.zeros(n, v, dtype=torch.int32, device=gaussians.device)
    with torch.no_grad():
        for index in tqdm(
            range(v),
            desc=f"lift ({config.samples_per_side}x{config.samples_per_side} rays/pixel)",
            disable=not progress,
        ):
            medians, _, view_hits = lift_view(gaussians, cameras[index], materials[index], masks[index], config)
            values[:, index], hits[:, index] = medians, view_hits.to(torch.int32)
    received = hits.sum(1, dtype=torch.long)
    seen = supported_views(hits, config.min_support)
    kept = seen.any(1)
    views_per_gaussian = seen[kept].sum(1).float()
    stats = {
        "gaussians_in": n,
        "gaussians_kept": int(kept.sum()),
        "gaussians_removed": int((~kept).sum()),
        "samples_per_side": config.samples_per_side,
        "view_size": [cameras[0].width, cameras[0].height] if cameras else None,
        "hits_per_gaussian_mean": float(received[kept].float().mean()) if kept.any() else 0.0,
        "hits_per_gaussian_median": float(received[kept].float().median()) if kept.any() else 0.0,
        "views_per_gaussian_mean": float(views_per_gaussian.mean()) if kept.any() else 0.0,
        "views_per_gaussian_min": int(views_per_gaussian.min()) if kept.any() else 0,
        "hit_views_per_gaussian_mean": float((hits[kept] > 0).sum(1).float().mean()) if kept.any() else 0.0,
        "min_support": config.min_support,
    }
    return LiftResult(
        values=values[kept], seen=seen[kept], kept=kept, view_names=list(view_names), stats=stats, hits=hits[kept]
    )


def save_lift(result: LiftResult, path: Path) -> None:
    save_torch_atomic(
        {
            "values": result.values.cpu(),
            "seen": result.seen.cpu(),
            "kept": result.kept.cpu(),
            "view_names": result.view_names,
            "stats": to_plain(result.stats),
            "hits": None if result.hits is None else result.hits.cpu(),
        },
        path,
    )


def load_lift(path: Path, device) -> LiftResult:
    """The lift stage's result, checked: a damaged file is named (with what to do), never trusted. In a run folder its
    Gaussians are checked against the geometry (or the masks stage's object) and its views against dataset.json."""
    path = Path(path)
    hint = stage_hint(path) or "delete it and rerun `matspray run` to lift again"
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - whatever a damaged file raises (unpickling, zip, EOF): the same clear message
        raise file_error(path, f"is not a readable lift result ({type(exc).__name__})", hint) from None

    def refuse(problem: str):
        return file_error(path, problem, hint)

    if not isinstance(data, dict) or not {"values", "seen", "kept", "view_names", "stats"} <= set(data):
        raise refuse("lacks the lift's values, seen, kept, view_names or stats")
    values, seen, kept, names, stats, hits = (
        data.get(k) for k in ("values", "seen", "kept", "view_names", "stats", "hits")
    )
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names) and isinstance(stats, dict)):
        raise refuse("its view_names are not a list of view names, or its stats no mapping")
    if not (isinstance(kept, torch.Tensor) and kept.dtype == torch.bool and kept.dim() == 1):
        raise refuse("its 'kept' flags are not a [N] bool tensor")
    count, views = int(kept.sum()), len(names)
    if not (
        isinstance(values, torch.Tensor) and values.is_floating_point() and tuple(values.shape) == (count, views, 5)
    ):
        raise refuse(f"its values are not [{count}, {views}, 5] (the kept Gaussians, the views, 5 channels)")
    if not bool(torch.isfinite(values).all()) or (
        count and not 0.0 <= float(values.min()) <= float(values.max()) <= 1.0
    ):
        raise refuse("its values are not finite numbers in [0, 1]")
    if not (isinstance(seen, torch.Tensor) and seen.dtype == torch.bool and tuple(seen.shape) == (count, views)):
        raise refuse(f"its 'seen' flags are not a [{count}, {views}] bool tensor")
    if hits is not None and not (
        isinstance(hits, torch.Tensor) and not hits.is_floating_point() and tuple(hits.shape) == (count, views)
    ):
        raise refuse(f"its hits are not a [{count}, {views}] integer tensor")
    run = path.parent.parent
    if stage_folder(path) is not None:
        try:
            masks = read_json(run / "masks" / "stage.json") if (run / "masks" / "stage.json").exists() else None
            lifted = (
                masks.get("inside") if isinstance(masks, dict) else vertex_count(run / "geometry" / "gaussians.ply")
            )
        except (OSError, ValueError):  # a damaged masks record: that stage is made again, and the lift with it
            lifted = None
        if isinstance(lifted, int) and lifted != len(kept):
            raise refuse(
                f"lifted {len(kept)} Gaussians, but the run's {'object' if masks else 'geometry'} has {lifted}"
            )
        try:
            train_views = RunDir(run).dataset().get("train_views")
        except MatsprayError:
            train_views = None  # a damaged dataset record is named by whatever reads it
        if train_views is not None and names != train_views:
            raise refuse(
                f"was lifted from {views} views ({', '.join(names[:3])}...), "
                f"not the run's {len(train_views)} training views"
            )
    return LiftResult(
        values=values.to(device),
        seen=seen.to(device),
        kept=kept.to(device),
        view_names=names,
        stats=stats,
        hits=None if hits is None else hits.to(device),
    )
