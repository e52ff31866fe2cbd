"""The `masks` stage of a capture without masks: the object region (matspray.geometry.region), the
Gaussians inside it, and every view's mask, their rendered alpha.

    masks/masks.pt         {"inside": [N] bool, "masks": {split: {view name: [H, W] uint8}}}
    masks/region.json      the region (sphere or box, the support plane, the rule)
    masks/{split}/{name}.png   the masks as grey images, for people
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data.images import save_torch_atomic, write_raw
from matspray.data.scene import Scene
from matspray.errors import DataError, MatsprayError, file_error
from matspray.gaussians import Gaussians
from matspray.geometry.ply import vertex_count
from matspray.geometry.region import ObjectRegion, object_region, regrown
from matspray.render.raster.rasterize import rasterize
from matspray.rundir import RunDir, read_record, stage_hint, write_json

SPLITS = ("train", "test")


@dataclass
class ObjectMasks:
    region: ObjectRegion
    inside: Tensor  # [N] bool over the geometry's Gaussians
    masks: dict[str, dict[str, Tensor]]  # split -> view name -> [H, W] float in [0, 1]
    source: Path | None = None  # the masks.pt read, for messages

    def apply(self, scene: Scene) -> None:
        """Give every view of `scene` its mask as alpha, and the scene the region's box as its bounds."""
        for split in SPLITS:
            for view in scene.split(split):
                mask = self.masks.get(split, {}).get(view.name)
                if mask is None or tuple(mask.shape) != (view.height, view.width):
                    problem = (
                        "has no mask"
                        if mask is None
                        else f"has a {mask.shape[1]}x{mask.shape[0]} mask, but the view is {view.width}x{view.height}"
                    )
                    raise file_error(
                        self.source or "object masks",
                        f"{split} view '{view.name}' {problem}",
                        masks_hint(self.source) if self.source else "",
                    )
        for split in SPLITS:
            for view in scene.split(split):
                view.alpha = self.masks[split][view.name].to(view.image.device)
        scene.bounds = self.region.bounds()


def object_alpha(gaussians: Gaussians, camera) -> Tensor:  # -> [H, W]
    """Coverage of `gaussians` in `camera`: their rendered alpha."""
    features = torch.zeros(len(gaussians), 1, device=gaussians.means.device)
    with torch.no_grad():
        return rasterize(gaussians, camera.to(gaussians.means.device), features).alpha.clamp(0.0, 1.0).cpu()


def compute_object_masks(
    gaussians: Gaussians, scene: Scene, object_bounds=None, progress: bool = True, region: ObjectRegion | None = None
) -> ObjectMasks:
    """The region (`object_bounds`, else `region`: the one the geometry focused on, else the automatic rule over the
    training cameras), the Gaussians inside it and the masks of every train and test view. A geometry that focused
    on its object drew the room coarsely, and the automatic rule, which finds the table among the room's Gaussians,
    would then miss it: the region found then is the object's, grown over the trained Gaussians (`regrown`)."""
    cameras = [v.camera for v in scene.train]
    if region is None or object_bounds is not None:
        region = object_region(gaussians.means, gaussians.opacities, cameras, object_bounds)
    else:  # found before the geometry knew the whole object: grown over its Gaussians now
        region = regrown(region, gaussians.means, gaussians.opacities, cameras)
    inside = region.contains(gaussians.means.detach()).cpu()
    if not inside.any():
        raise DataError(
            f"the object region ({region.describe()}) holds none of the {len(inside)} Gaussians; "
            "give one that does (setting object_bounds)"
        )
    obj = gaussians.subset(inside.to(gaussians.means.device))
    views = [(split, view) for split in SPLITS for view in scene.split(split)]
    masks: dict[str, dict[str, Tensor]] = {split: {} for split in SPLITS}
    for split, view in tqdm(views, desc="masks", unit="view", disable=not progress):
        masks[split][view.name] = object_alpha(obj, view.camera)
    return ObjectMasks(region, inside, masks)


def write_object_masks(folder: Path, masks: ObjectMasks) -> None:
    folder = Path(folder)
    for split, by_name in masks.masks.items():
        for name, mask in by_name.items():
            write_raw(folder / split / f"{name}.png", mask[..., None])
    quantised = {
        split: {name: (m * 255).round().to(torch.uint8) for name, m in by_name.items()}
        for split, by_name in masks.masks.items()
    }
    save_torch_atomic({"inside": masks.inside, "masks": quantised}, folder / "masks.pt")
    write_json(folder / "region.json", masks.region.to_json())


def masks_hint(path: Path) -> str:
    return stage_hint(path) or f"delete {Path(path).parent} and rerun `matspray run` to make the masks again"


def read_region(folder: Path) -> ObjectRegion | None:
    """The object region of a masks stage (RUN/masks), without reading its masks; None where the run has none."""
    path = Path(folder) / "region.json"
    if not path.exists():
        return None
    data = read_record(path, masks_hint(path))

    def numbers(v, n):
        return (
            isinstance(v, list)
            and len(v) == n
            and all(not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in v)
        )

    radius = data.get("radius") if isinstance(data, dict) else None
    sphere = (
        radius is not None
        and numbers([radius], 1)
        and radius > 0
        and data.get("low") is None
        and data.get("high") is None
    )
    box = (
        radius is None
        and isinstance(data, dict)
        and numbers(data.get("low"), 3)
        and numbers(data.get("high"), 3)
        and all(lo < hi for lo, hi in zip(data["low"], data["high"]))
    )
    if not (
        isinstance(data, dict)
        and numbers(data.get("center"), 3)
        and (sphere or box)
        and (data.get("plane") is None or numbers(data.get("plane"), 4))
        and isinstance(data.get("rule", "given"), str)
    ):
        raise file_error(
            path,
            "does not describe an object region (a sphere or a box, finite, with an optional plane)",
            masks_hint(path),
        )
    region = ObjectRegion.from_json(data)
    if not torch.isfinite(region.bounds()).all():  # the scene's bounds, in float32
        raise file_error(path, "describes an object region too large for the scene's bounds", masks_hint(path))
    return region


def read_object_masks(folder: Path) -> ObjectMasks:
    """The masks stage of a run (RUN/masks): its region, the Gaussians inside, and every view's mask, checked against
    the run's geometry (RUN/geometry/gaussians.ply) and views (RUN/dataset.json) where the folder is in a run."""
    folder = Path(folder)
    path = folder / "masks.pt"
    hint = masks_hint(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - whatever a damaged file raises (unpickling, zip, EOF): the same clear message
        raise file_error(path, f"is not a readable masks file ({type(exc).__name__})", hint) from None
    inside, by_split = (data.get("inside"), data.get("masks")) if isinstance(data, dict) else (None, None)
    if not (isinstance(inside, Tensor) and inside.dtype == torch.bool and inside.dim() == 1 and bool(inside.any())):
        raise file_error(path, "holds no 'inside' flags (a [N] bool tensor marking some Gaussians)", hint)
    if not (
        isinstance(by_split, dict)
        and set(by_split) == set(SPLITS)
        and all(isinstance(v, dict) for v in by_split.values())
    ):
        raise file_error(path, f"holds no masks of the {' and '.join(SPLITS)} views", hint)
    for split, by_name in by_split.items():
        shapes = {
            tuple(m.shape) if isinstance(m, Tensor) and m.dtype == torch.uint8 and m.dim() == 2 and m.numel() else None
            for m in by_name.values()
        }
        if None in shapes or len(shapes) > 1 or not all(isinstance(name, str) for name in by_name):
            raise file_error(path, f"the masks of the {split} views are not [H, W] 8-bit images of one size", hint)
    count = vertex_count(folder.parent / "geometry" / "gaussians.ply")
    if count is not None and count != len(inside):
        raise file_error(path, f"marks {len(inside)} Gaussians, but the run's geometry has {count}", hint)
    try:
        identity = RunDir(folder.parent).dataset() if (folder.parent / "dataset.json").exists() else None
    except MatsprayError:
        identity = None  # a damaged dataset record is named by whatever reads it
    for split in SPLITS if identity is not None else ():
        if f"{split}_views" in identity and sorted(by_split[split]) != sorted(identity[f"{split}_views"]):
            raise file_error(path, f"its {split} masks are of other views than the run's", hint)
    region = read_region(folder)
    if region is None:
        raise file_error(folder / "region.json", "does not exist", hint)
    masks = {split: {name: m.float() / 255.0 for name, m in by_name.items()} for split, by_name in by_split.items()}
    return ObjectMasks(region, inside, masks, path)
