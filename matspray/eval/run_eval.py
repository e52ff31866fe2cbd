"""`matspray eval`: every figure of a run against the ground truth of a `matspray synth` object.

For each asset in the run (the full method and any ablation variant) and each test view:
  relighting  the asset rendered under every held-out light (`envmaps/{env}.exr`) vs Mitsuba's
              render of the same view (`test/{view}_relight_{env}.png`)
  materials   rasterized base color, roughness, metallic vs the true maps (`test/{view}_{channel}.png`)
and, as the baseline the method must beat, the raw 2D predictions of the test views (when the run's
predictor can make them). Everything is compared on the object (ground-truth mask, shared background)
and, under the same key + "_union", over the object and its silhouette (each image composited with its
own alpha, scored over the union of the two silhouettes; see `matspray.eval.masked`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

from matspray.data import Scene, View, load_run_scene, read_image
from matspray.errors import DataError, file_error
from matspray.eval.evaluate import average_metrics, evaluate_images, pooled_union_psnr
from matspray.eval.lpips import load_lpips
from matspray.eval.masked import align_scale
from matspray.eval.metallic import metallic_psnr_over_objects
from matspray.eval.page.paths import object_name
from matspray.eval.tables import UNION, write_tables
from matspray.geometry.evaluate import true_normals
from matspray.geometry.region import mask_iou
from matspray.method.asset import read_asset
from matspray.method.masks import ObjectMasks, read_object_masks
from matspray.method.relight import render_gbuffer
from matspray.predictors import NO_PREDICTOR, PredictorOptions, make_predictor, options_for_dataset, predict_views
from matspray.predictors.ground_truth import read_ground_truth, read_ground_truth_coverage
from matspray.predictors.kinds import PredictorSpec, predictor_kinds
from matspray.presets import ABLATION, BASELINE, LABELS, MAPLESS_DEFAULT, SOFTMAX_ABLATION, asset_stage
from matspray.render.backend import rendering_with
from matspray.render.shade.deferred import shade_gbuffer
from matspray.render.shade.envmap import EnvironmentMap
from matspray.rundir import RunDir, write_json

EVAL_ENV_HEIGHT = 64  # relighting maps are prefiltered from this many rows (x 2 columns)


@dataclass
class GroundTruth:
    mask: torch.Tensor  # [H, W]
    basecolor: torch.Tensor  # [H, W, 3] linear
    roughness: torch.Tensor  # [H, W]
    metallic: torch.Tensor  # [H, W]
    relit: dict[str, torch.Tensor]  # env name -> [H, W, 3] linear
    normals: torch.Tensor | None = None  # [H, W, 3] world, unit (the synth object's `{view}_normal.exr`); None: none


def relight_env_names(view: View) -> list[str]:
    prefix = f"{view.name}_relight_"
    return sorted(p.stem[len(prefix) :] for p in view.path.parent.glob(f"{prefix}*.png"))


def read_view_truth(view: View) -> GroundTruth:
    maps = read_ground_truth(view)
    mask = (
        view.alpha if view.alpha is not None else read_ground_truth_coverage(view)
    )  # a photo without mask: the true one
    relit = {}
    for env in relight_env_names(view):
        rgb, _ = read_image(view.path.with_name(f"{view.name}_relight_{env}.png"))
        relit[env] = rgb
    return GroundTruth(mask, maps.basecolor, maps.roughness, maps.metallic, relit, true_normals(view))


def relight_light(data: Path, name: str) -> EnvironmentMap:
    """The held-out light `name` of a synthetic object (`envmaps/NAME.exr`) at the size evaluation relights with."""
    path = Path(data) / "envmaps" / f"{name}.exr"
    if not path.exists():
        raise file_error(path, f"the held-out light '{name}' has relit ground truth but no environment map")
    return EnvironmentMap.from_file(path, height=EVAL_ENV_HEIGHT)


def load_relight_lights(data: Path, names: list[str], device="cpu"):
    """The held-out lights {name: PrefilteredEnvironment}, prefiltered on `device`."""
    return {name: relight_light(data, name).to(device).prefilter() for name in names}


def unpremultiply(rgb: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:  # [H, W, 3], [H, W] -> [H, W, 3]
    return torch.where(alpha[..., None] > 1e-4, rgb / alpha[..., None].clamp_min(1e-4), torch.zeros_like(rgb))


@dataclass
class ViewRenders:
    """What an asset shows at one test view: relit images and its material maps (clamped to [0, 1])."""

    relit: dict[str, torch.Tensor]  # env name -> [H, W, 3] linear, straight (not premultiplied) colour
    base_color: torch.Tensor  # [H, W, 3] linear
    roughness: torch.Tensor  # [H, W]
    metallic: torch.Tensor  # [H, W]
    alpha: torch.Tensor  # [H, W] coverage
    normals: torch.Tensor | None = None  # [H, W, 3] world, blended (any length); None: the renderer has none


def asset_renders(asset, view: View, lights: dict) -> ViewRenders:
    """The Gaussian asset's G-buffer at `view`, shaded under every light."""
    camera = view.camera.to(asset.gaussians.device)
    with torch.no_grad():
        # with visibility each light casts its own shadows; the material channels are the same in every G-buffer
        lit = (
            {env: render_gbuffer(asset, camera, light) for env, light in lights.items()}
            if asset.visibility is not None
            else {}
        )
        gbuffer = next(iter(lit.values())) if lit else render_gbuffer(asset, camera)
        relit = {}
        for env, light in lights.items():
            shaded = lit.get(env, gbuffer)
            relit[env] = unpremultiply(shade_gbuffer(shaded, camera, light), shaded.alpha).cpu()
        return ViewRenders(
            relit,
            gbuffer.base_color.cpu().clamp(0, 1),
            gbuffer.roughness.cpu().clamp(0, 1),
            gbuffer.metallic.cpu().clamp(0, 1),
            gbuffer.alpha.cpu(),
            gbuffer.normals.cpu(),
        )


def evaluate_asset(
    asset, views: list[View], truths: list[GroundTruth], lights: dict, lpips, aligned: bool = False
) -> dict:
    """Per-view and averaged metrics of one asset: relighting (per light and overall) and materials."""
    return score_renders(
        (asset_renders(asset, view, lights) for view in views), views, truths, list(lights), lpips, aligned
    )


def score_renders(
    renders, views: list[View], truths: list[GroundTruth], env_names: list[str], lpips, aligned: bool = False
) -> dict:
    """Per-view and averaged metrics of any renderer's `renders` (one ViewRenders per view) against the truth.

    Every figure twice: under its key the object-mask (GT) figure, and under the key + "_union" the
    silhouette-counting one, where the render is composited with its own alpha and scored over the
    union of its silhouette and the true one (`evaluate_images`), so a mesh and a Gaussian asset are
    judged alike at and outside the silhouette.
    """
    per_view = []
    keys = ("relighting", "basecolor", "roughness", "metallic") + (
        ("relighting_aligned", "basecolor_aligned") if aligned else ()
    )
    records: dict[str, list] = {
        key + suffix: [] for key in keys for suffix in ("", UNION)
    }  # per-image metrics of all views (and lights)
    preds_metal, alphas_metal, truths_metal, masks_metal = [], [], [], []

    def both(key: str, pred, target, truth: GroundTruth, alpha, encoding: str = "srgb") -> tuple[dict, dict]:
        scored = (
            evaluate_images(pred, target, truth.mask, lpips, encoding=encoding),
            evaluate_images(pred, target, truth.mask, lpips, encoding=encoding, pred_alpha=alpha),
        )
        records[key].append(scored[0])
        records[key + UNION].append(scored[1])
        return scored

    for view, truth, render in zip(views, truths, renders):
        record = {"view": view.name, "relighting": {}, "relighting" + UNION: {}}
        for env in env_names:
            rgb = render.relit[env]
            record["relighting"][env], record["relighting" + UNION][env] = both(
                "relighting", rgb, truth.relit[env], truth, render.alpha
            )
            if aligned:
                both(
                    "relighting_aligned",
                    align_scale(rgb, truth.relit[env], truth.mask),
                    truth.relit[env],
                    truth,
                    render.alpha,
                )
        base, rough, metal = render.base_color, render.roughness, render.metallic
        record["basecolor"], record["basecolor" + UNION] = both("basecolor", base, truth.basecolor, truth, render.alpha)
        record["roughness"], record["roughness" + UNION] = both(
            "roughness", rough[..., None], truth.roughness[..., None], truth, render.alpha, "raw"
        )
        record["metallic"], record["metallic" + UNION] = both(
            "metallic", metal[..., None], truth.metallic[..., None], truth, render.alpha, "raw"
        )
        if aligned:
            both(
                "basecolor_aligned",
                align_scale(base, truth.basecolor, truth.mask),
                truth.basecolor,
                truth,
                render.alpha,
            )
        preds_metal.append(metal)
        alphas_metal.append(render.alpha)
        truths_metal.append(truth.metallic)
        masks_metal.append(truth.mask)
        error = normal_error_deg(render, truth)
        if error is not None:
            record["normal_error_deg"] = error
        per_view.append(record)
    summary = {key: average_metrics(values) for key, values in records.items()}
    normal_errors = [r["normal_error_deg"] for r in per_view if "normal_error_deg" in r]
    if normal_errors:  # mean angle between the rendered and the true normals on the object, over the test views
        summary["normals"] = {"error_deg": sum(normal_errors) / len(normal_errors), "views": len(normal_errors)}
    add_pooled_metallic(summary, preds_metal, alphas_metal, truths_metal, masks_metal)
    for env in env_names:
        summary[f"relighting_{env}"] = average_metrics([r["relighting"][env] for r in per_view])
        summary[f"relighting_{env}{UNION}"] = average_metrics([r["relighting" + UNION][env] for r in per_view])
    return {"summary": summary, "per_view": per_view}


def normal_error_deg(render, truth: GroundTruth) -> float | None:
    """Mean angle (degrees) between the rendered and the true normals on the object; None without both or a mask."""
    if truth.normals is None or render.normals is None or not bool((truth.mask > 0.5).any()):
        return None
    # unsigned: the shading normal is flipped to face the camera, a true normal seen from behind is not
    cosine = (F.normalize(render.normals, dim=-1) * truth.normals).sum(-1).abs().clamp(max=1.0)
    return float(torch.rad2deg(torch.acos(cosine))[truth.mask > 0.5].mean())


def pooled_metallic(preds: list, truths: list, masks: list, mean_of_views: float | None) -> dict:
    """One object's metallic figures from its views' maps [H, W] each: the PSNR of the error pooled over the views
    with the paper's infinity rule (`psnr`, `psnr_infinite`) and the mean of the views' own PSNRs (`psnr_views`)."""
    metallic = metallic_psnr_over_objects([(torch.stack(preds), torch.stack(truths), torch.stack(masks))])
    return {
        "psnr": metallic.mean if metallic.mean is not None else math.inf,
        "psnr_infinite": metallic.infinite,
        "psnr_views": mean_of_views,
    }


def add_pooled_metallic(summary: dict, preds: list, alphas: list, truths: list, masks: list) -> None:
    """The metallic PSNR pooled over the views with the paper's infinity rule, under both regions, into `summary`."""
    summary["metallic"].update(pooled_metallic(preds, truths, masks, summary["metallic"]["psnr"]), objects=1)
    union = pooled_union_psnr(preds, alphas, truths, masks)
    summary["metallic" + UNION].update(psnr=union, psnr_infinite=int(math.isinf(union)), objects=1)


def evaluate_predictions(maps: dict, views: list[View], truths: list[GroundTruth], lpips) -> dict:
    """The raw 2D predictions of the test views against the truth (what lifting starts from).

    Metallic is scored by the rule of the 3D assets' metallic (`pooled_metallic`: the error pooled over the
    views), so that "3D above 2D" compares like with like; the mean of the views' own PSNRs, which forgives a
    prediction whose spurious metal sits in a few views, stays beside it as `psnr_views`.
    """
    records = {"basecolor": [], "roughness": [], "metallic": []}
    metals, truth_metals, masks = [], [], []
    for view, truth in zip(views, truths):
        m = maps[view.name]
        records["basecolor"].append(evaluate_images(m.basecolor.clamp(0, 1), truth.basecolor, truth.mask, lpips))
        records["roughness"].append(
            evaluate_images(m.roughness[..., None], truth.roughness[..., None], truth.mask, lpips, encoding="raw")
        )
        records["metallic"].append(
            evaluate_images(m.metallic[..., None], truth.metallic[..., None], truth.mask, lpips, encoding="raw")
        )
        metals.append(m.metallic.clamp(0, 1))
        truth_metals.append(truth.metallic)
        masks.append(truth.mask)
    summary = {name: average_metrics(values) for name, values in records.items()}
    if metals:
        summary["metallic"].update(pooled_metallic(metals, truth_metals, masks, summary["metallic"]["psnr"]))
    return summary


def check_synthetic(scene: Scene) -> None:
    if not scene.test:
        raise DataError(f"{scene.source}: no test views to evaluate on")
    missing = [v.name for v in scene.test if not v.path.with_name(f"{v.name}_basecolor.png").exists()]
    if missing:
        raise file_error(
            scene.source,
            f"test views without ground-truth material maps: {', '.join(missing[:5])}",
            "evaluation needs a `matspray synth` object (or the same layout of ground truth)",
        )


def predict_test_views(run_dir: Path, views: list[View]) -> tuple[dict | None, str]:
    """Raw 2D predictions of the test views by the run's predictor, when it can make them here."""
    config = RunDir(run_dir).config()
    spec, given = config.get("predictor", ""), config.get("predictor_options", {})
    if spec == NO_PREDICTOR:
        return None, "no 2D predictions: the run had none (--predictor none)"
    if not isinstance(spec, str) or not isinstance(given, dict):
        return (
            None,
            f"raw 2D predictions of test views not evaluated ({RunDir(run_dir).path('config.yaml')} names "
            "no readable predictor)",
        )
    kind = predictor_kinds().get(PredictorSpec.parse(spec).kind)
    if kind is None or not kind.reruns_for_eval:
        return None, f"raw 2D predictions of test views not evaluated (predictor '{spec}' would have to run again)"
    try:
        stored = PredictorOptions(**given)
    except TypeError:  # a key PredictorOptions does not have
        return (
            None,
            "raw 2D predictions of test views not evaluated (unknown predictor_options in "
            f"{RunDir(run_dir).path('config.yaml')})",
        )
    try:
        options = options_for_dataset(spec, stored, RunDir(run_dir).dataset().get("source"))
        predictor = make_predictor(spec, options, notify=lambda _: None)
        return predict_views(views, predictor, notify=lambda _: None), f"raw 2D predictions: {spec}"
    except DataError as exc:
        return None, f"raw 2D predictions of test views not evaluated: {exc}"


def evaluate_run(
    run_dir,
    data=None,
    lpips_weights=None,
    aligned: bool = False,
    progress: bool = True,
    device="cpu",
    backend: str = "torch",
    scene: Scene | None = None,
) -> dict:
    """Evaluate every asset of `run_dir` on the dataset's test views, rendered on `device` with the rasterizer
    `backend` (both resolved); writes eval/metrics.json and eval/tables.md and returns the metrics. `scene`: the
    dataset already loaded (as `data` at the run's downscale), so that it is not read twice."""
    run = RunDir(run_dir).require()
    identity = run.dataset()
    data = Path(data) if data is not None else Path(identity["source"])
    if scene is None:
        scene = load_run_scene(run, data)
    if [v.name for v in scene.train] != identity["train_views"]:
        raise DataError(f"{run.root}: this run was made from {identity['source']}, not from {data}")
    check_synthetic(scene)
    lpips, lpips_source = load_lpips(lpips_weights)
    truths = [read_view_truth(v) for v in scene.test]
    env_names = sorted(set.intersection(*(set(t.relit) for t in truths)))
    lights = load_relight_lights(data, env_names, device)
    metrics = {
        "title": f"MatSpray evaluation: {object_name(data)}",  # tables.md is shared: no path of the machine
        "lpips": lpips_source,
        "notes": [],
        "relight_envs": env_names,
    }
    if not env_names:
        metrics["notes"].append("no relit ground truth in the dataset: relighting not evaluated")
    variants = {}
    stages = [(v, asset_stage(v)) for v in run.asset_variants()]
    for variant, stage in tqdm(stages, desc="eval", disable=not progress):
        with rendering_with(backend):
            variants[variant] = evaluate_asset(
                read_asset(run.path(stage), device=device), scene.test, truths, lights, lpips, aligned
            )
    predictions, note = predict_test_views(run.root, scene.test)
    metrics["notes"].append(note)
    if predictions is not None:
        metrics["predictions_2d"] = evaluate_predictions(predictions, scene.test, truths, lpips)
    metrics["variants"] = variants
    if run.path("masks", "masks.pt").exists():
        metrics["masks"] = mask_agreement(read_object_masks(run.path("masks")), scene.test, truths)
    metrics.update(paper_tables(variants, metrics.get("predictions_2d"), run.timings()))
    write_json(run.path("eval", "metrics.json"), metrics)
    write_tables(run.path("eval", "tables.md"), metrics)
    return metrics


def mask_agreement(masks: ObjectMasks, views: list[View], truths: list[GroundTruth]) -> dict:
    """IoU of a capture's object masks (made from its geometry) against the true masks of the test views."""
    ious = {v.name: mask_iou(masks.masks["test"][v.name], t.mask) for v, t in zip(views, truths)}
    values = list(ious.values())
    return {
        "iou_mean": sum(values) / len(values),
        "iou_min": min(values),
        "views": ious,
        "region": masks.region.to_json(),
    }


def paper_tables(variants: dict, predictions: dict | None, timings: dict) -> dict:
    """The table dicts `matspray.eval.tables` renders, from per-variant summaries."""
    # each figure under the object mask (GT) and, as "<row>_union", counting the silhouette; the raw 2D
    # predictions have no silhouette of their own (they are masked by the input), so no union rows
    rows = tuple(
        row + suffix
        for row in ("relighting", "basecolor", "roughness", "metallic", "relighting_aligned", "basecolor_aligned")
        for suffix in ("", UNION)
    )
    table1 = {}
    if "full" in variants:
        summary = variants["full"]["summary"]
        table1["Ours"] = {row: summary[row] for row in rows if row in summary}
    for name in (BASELINE, MAPLESS_DEFAULT):  # the paper's baseline column (no 2D prior), and the user's asset without
        if name in variants:  # maps beside it
            summary = variants[name]["summary"]
            table1[LABELS[name]] = {row: summary[row] for row in rows if row in summary}
    if predictions is not None:
        table1["2D predictions"] = {row: predictions[row] for row in ("basecolor", "roughness", "metallic")}
    table2 = {LABELS[v]: variants[v]["summary"]["relighting"] for v in ABLATION if v in variants}
    softmax = {LABELS[v]: variants[v]["summary"]["relighting"] for v in SOFTMAX_ABLATION if v in variants}
    union = {
        key + UNION: {
            LABELS[v]: variants[v]["summary"]["relighting" + UNION]
            for v in names
            if v in variants and "relighting" + UNION in variants[v]["summary"]
        }
        for key, names in (("table2", ABLATION), ("softmax", SOFTMAX_ABLATION))
    }
    stage_names = {
        "materials2d": "predict",
        "geometry": "geometry",
        "lift": "lift",
        "visibility": "visibility",
        "asset": "refine",
    }
    stages = {stage_names[k]: v for k, v in timings.items() if k in stage_names}
    return {
        "table1": table1,
        "table2": table2,
        "softmax": softmax,
        **{k: v for k, v in union.items() if v},
        "timings": {"Ours (this machine)": stages} if stages else {},
    }
