"""The `masks` stage of a capture without masks: the object region (matspray.objectregion), the
Gaussians inside it, and every view's mask, their rendered alpha.

    masks/masks.pt         {"inside": [N] bool, "masks": {split: {view name: [H, W] uint8}}}
    masks/region.json      the region (sphere or box, the support plane, the rule)
    masks/{split}/{name}.png   the masks as grey images, for people
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from tqdm import tqdm

from matspray.data.images import save_torch_atomic, write_raw
from matspray.data.scene import Scene
from matspray.errors import DataError
from matspray.gaussians import Gaussians
from matspray.objectregion import ObjectRegion, auto_region, given_region
from matspray.render.rasterize import rasterize
from matspray.rundir import write_json

SPLITS = ("train", "test")


@dataclass
class ObjectMasks:
    region: ObjectRegion
    inside: Tensor  # [N] bool over the geometry's Gaussians
    masks: dict[str, dict[str, Tensor]]  # split -> view name -> [H, W] float in [0, 1]

    def apply(self, scene: Scene) -> None:
        """Give every view of `scene` its mask as alpha, and the scene the region's box as its bounds."""
        for split in SPLITS:
            for view in scene.split(split):
                view.alpha = self.masks[split][view.name].to(view.image.device)
        scene.bounds = self.region.bounds()


def object_alpha(gaussians: Gaussians, camera) -> Tensor:  # -> [H, W]
    """Coverage of `gaussians` in `camera`: their rendered alpha."""
    features = torch.zeros(len(gaussians), 1, device=gaussians.means.device)
    with torch.no_grad():
        return rasterize(gaussians, camera.to(gaussians.means.device), features).alpha.clamp(0.0, 1.0).cpu()


def compute_object_masks(gaussians: Gaussians, scene: Scene, object_bounds=None, progress: bool = True) -> ObjectMasks:
    """The region (`object_bounds`, else the automatic rule over the training cameras), the Gaussians inside
    it and the masks of every train and test view."""
    if object_bounds is not None:
        region = given_region(object_bounds)
    else:
        region = auto_region(gaussians.means, gaussians.opacities, [v.camera for v in scene.train])
    inside = region.contains(gaussians.means.detach()).cpu()
    if not inside.any():
        raise DataError(f"the object region ({region.describe()}) holds none of the {len(inside)} Gaussians; "
                        "give one that does with --object-bounds")
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
    quantised = {split: {name: (m * 255).round().to(torch.uint8) for name, m in by_name.items()} for split, by_name in masks.masks.items()}
    save_torch_atomic({"inside": masks.inside, "masks": quantised}, folder / "masks.pt")
    write_json(folder / "region.json", masks.region.to_json())


def read_region(folder: Path) -> ObjectRegion | None:
    """The object region of a masks stage (RUN/masks), without reading its masks; None where the run has none."""
    path = Path(folder) / "region.json"
    return ObjectRegion.from_json(json.loads(path.read_text())) if path.exists() else None


def read_object_masks(folder: Path) -> ObjectMasks:
    folder = Path(folder)
    data = torch.load(folder / "masks.pt", weights_only=False)
    masks = {split: {name: m.float() / 255.0 for name, m in by_name.items()} for split, by_name in data["masks"].items()}
    return ObjectMasks(read_region(folder), data["inside"], masks)
