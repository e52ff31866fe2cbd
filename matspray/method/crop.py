"""The `crop` stage of a capture without masks: the object region found on the sparse points, before any training,
and the windows each photo is cut to around it (matspray.data.crop), kept as RUN/crop/crop.json:

    {"plan": {"size": [W, H], "windows": {view name: [left, top, right, bottom]}} or null (photos used whole),
     "region": the object region (matspray.geometry.region) or null, "message": what was decided, in one line}
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from matspray.data.crop import (
    CROP_FILE,
    MIN_POINTS,
    WHOLE_FRAME,
    CropConfig,
    CropPlan,
    crop_window,
    object_box,
    read_crop_plan,
    read_crop_record,
)
from matspray.data.loader import load_scene
from matspray.data.scene import Scene, View
from matspray.files import write_json
from matspray.geometry.region import ObjectRegion, object_region
from matspray.rundir import RunDir, timed


def plan_crop(
    train: list[View], test: list[View], points: Tensor | None, downscale: float, config: CropConfig, object_bounds=None
) -> tuple[CropPlan | None, ObjectRegion | None, str]:
    """The windows of the `train` and `test` views (at the working size, shrunk by `downscale` from their photos)
    around the sparse `points` [P, 3] inside the object region (`object_bounds`, else the automatic rule on the
    points and the training cameras), the region, and one line saying what was decided. The plan is None (the line
    says why) when the photos are not cut."""
    if not config.enabled:
        return None, None, "crop: off (crop.enabled=false); the photos are used whole"
    if downscale <= 1.0:
        return None, None, "crop: the photos are no larger than the working size; cutting them would add no detail"
    if points is None or len(points) < MIN_POINTS:
        return None, None, "crop: no sparse points to find the object with; the photos are used whole"
    region = object_region(points, torch.ones(len(points)), [v.camera for v in train], object_bounds)
    inside = points[region.contains(points).to(points.device)]
    if len(inside) < MIN_POINTS:
        return None, region, f"crop: {len(inside)} sparse points in the {region.describe()}; the photos are used whole"
    views = train + test
    boxes = [object_box(inside, v.camera, config.quantile) for v in views]
    least = 1 / downscale  # the window's side in the photo's pixels is at least the working size: nothing enlarged
    windows = {v.name: crop_window(box, v.width, v.height, config.margin, least) for v, box in zip(views, boxes)}
    plan = CropPlan((train[0].width, train[0].height), windows)
    gain = 1.0 / plan.mean_side()
    if gain < config.min_gain:
        return None, region, f"crop: the object fills most of the photos ({gain:.2f}x by cutting); photos used whole"
    whole = sum(w == WHOLE_FRAME for w in windows.values())
    kept = f"; {whole} view(s) keep the whole photo" if whole else ""
    return plan, region, f"crop: each photo cut to its object, {gain:.2f}x the pixels across on average{kept}"


def write_crop(folder: Path, plan: CropPlan | None, region: ObjectRegion | None, message: str) -> None:
    """RUN/crop/crop.json: the plan (null: the photos are used whole), the region it was found in, and why."""
    record = {
        "plan": None if plan is None else plan.to_json(),
        "region": None if region is None else region.to_json(),
        "message": message,
    }
    write_json(Path(folder) / CROP_FILE, record)


def read_crop_region(folder: Path) -> ObjectRegion | None:
    """The region a run's crop stage cut around (None when it has none)."""
    return read_crop_record(folder, "region", ObjectRegion.from_json)


def crop_stage(
    run: RunDir, fingerprint: str, scene: Scene, config: CropConfig, object_bounds, log: Callable[[str], None]
) -> tuple[Scene, ObjectRegion | None]:
    """The run's stage `crop`: the windows of `scene`'s views around its sparse points (`plan_crop`), kept in
    RUN/crop/crop.json and reused while its record holds `fingerprint`. Returns the scene read again through them
    (its points and bounds kept) and the region they were cut around; `scene` itself and None when nothing is cut."""
    folder = run.path("crop")
    if run.stage_done("crop", fingerprint, [CROP_FILE]):
        plan, region = read_crop_plan(folder), read_crop_region(folder)
    else:
        with timed() as timer:
            views, points = (scene.train, scene.test), scene.points
            plan, region, message = plan_crop(*views, points, scene.downscale, config, object_bounds)
            write_crop(folder, plan, region, message)
        run.finish_stage("crop", fingerprint, config, timer.seconds, {"message": message}, timer.peak_mib)
        log(message)
    if plan is None:
        return scene, None
    cut = load_scene(scene.source, downscale=scene.downscale, crop=plan)
    cut.points, cut.point_colors, cut.bounds = scene.points, scene.point_colors, scene.bounds
    return cut, region
