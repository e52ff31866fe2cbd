"""One-sided table-top captures: how much of the object the object region holds, and the masks' IoU.

    python -m benchmarks.one_sided [--tabletops white-on-dark dark-on-light] [--seeds 0 1 2] [--out runs/one-sided]
                                   [--resolution 64] [--views 16] [--fill 1.1] [--cameras front] [--shape random]

(`--cameras sphere --fill 0.92 --tabletops grey --shape composite --seeds 3`: a table-top capture like those of
`benchmarks.unmasked`, for the same scores.)

Makes `matspray synth` captures like a hand-held one of an object on a table (`SynthConfig`: `cameras="front"`, a
frontal half of views up to 45 degrees; `fill`: the object fills the frame; `tabletop`: a white object on a dark
wooden table or a dark one on a light table; the photos show the training light behind, no masks). Then, without
training Gaussian Splatting, it takes where each pixel's ray first meets the scene (the object, from its true depth;
the table, by the ray's hit on its plane; otherwise far behind, as the room's Gaussians are): the points that
Gaussians fitting the training photos exactly would sit on, seen only where the cameras saw. On those of the
training views (`gaussians`) and on a sparse tenth of them (`sparse`, as the crop stage finds the region on
structure from motion's points), it runs the automatic rule (matspray.geometry.region) and prints the region, the
framing radius that capped it before the fix and the object's bounding radius, the shares of the object's and the
table's first hits (every view) it holds, and the IoU against the true masks of every view (train and test; a
pixel is in the mask when its first hit is in the region), mean and worst. No Gaussians are trained or rendered:
this measures the region alone (the full method on such a capture: `python -m benchmarks.unmasked`).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import torch

from matspray.data import load_scene
from matspray.data.scene import Scene, cameras_focus
from matspray.geometry.region import ObjectRegion, auto_region, mask_iou
from matspray.predictors.ground_truth import read_ground_truth_coverage, read_ground_truth_depth
from matspray.synth import SynthConfig, make_object

TABLETOPS = ("white-on-dark", "dark-on-light")
FAR = 6.0  # the room's Gaussians sit this many camera distances away along a pixel's ray
SPARSE_EVERY = 10  # the sparse points: every tenth pixel Gaussian (structure from motion's points are sparse)


def one_sided_config(
    tabletop: str,
    seed: int,
    resolution: int = 64,
    views: int = 16,
    fill: float = 1.1,
    test_views: int = 4,
    spp: int = 8,
    cameras: str = "front",
    shape: str = "random",
) -> SynthConfig:
    """A capture like the held-out skull's: from one side, the object filling the frame, on a textured table (or,
    with other `cameras`, `fill` and the grey `tabletop`, one like the table-top captures before it)."""
    return SynthConfig(
        shape=shape,
        seed=seed,
        resolution=resolution,
        train_views=views,
        test_views=test_views,
        spp=spp,
        env_height=32,
        texture_height=64,
        background="env",
        ground=True,
        cameras=cameras,
        fill=fill,
        tabletop=tabletop,
    )


def make_capture(config: SynthConfig, out: Path) -> Path:
    if not (out / "scene.json").exists():
        make_object(config, out, progress=False, notify=lambda _: None)
    return out


@dataclass
class FirstHits:
    points: torch.Tensor  # [P, 3] where each pixel's ray first meets the scene
    kind: torch.Tensor  # [P] int: 0 object, 1 table, 2 far behind


def first_hits(view, ground_z: float) -> FirstHits:
    """Every pixel's first hit: the object where the true coverage is at least half (its true depth: the mean over
    the subpixel rays that hit), else the table plane z = `ground_z` in front of the camera, else FAR camera
    distances away along the ray."""
    camera = view.camera
    directions = camera.pixel_directions().double().reshape(-1, 3)  # [P, 3] at camera z = 1
    depth = read_ground_truth_depth(view).double().reshape(-1)
    covered = (read_ground_truth_coverage(view).reshape(-1) >= 0.5) & (depth > 0)
    center = camera.center.double()
    table_t = (ground_z - center[2]) / directions[:, 2]  # camera z of the table's hit
    on_table = ~covered & (table_t > 0)
    far = torch.full_like(depth, FAR * float(center.norm()))
    z = torch.where(covered, depth, torch.where(on_table, table_t, far))
    kind = torch.where(covered, 0, torch.where(on_table, 1, 2))
    return FirstHits(center + directions * z[:, None], kind)


def score(region: ObjectRegion, scene: Scene, ground_z: float) -> dict:
    """What `region` holds of the object's and the table's first hits over every view (train and test), and the IoU
    of each view's mask (its pixels whose first hit is in the region: the mask of Gaussians that fit the photos
    exactly) against its true mask: mean and worst."""
    held = {0: [], 1: []}
    ious = []
    for view in scene.train + scene.test:
        hits = first_hits(view, ground_z)
        inside = region.contains(hits.points)
        for kind in held:
            held[kind].append(inside[hits.kind == kind])
        mask = inside.reshape(view.height, view.width).float()
        ious.append(mask_iou(mask, read_ground_truth_coverage(view)))
    return {
        "object_held": float(torch.cat(held[0]).double().mean()),
        "table_held": float(torch.cat(held[1]).double().mean()),
        "iou_mean": sum(ious) / len(ious),
        "iou_min": min(ious),
    }


def cloud(scene: Scene, ground_z: float) -> torch.Tensor:  # -> [P, 3]
    """The first hits of the training views' pixels: where Gaussians that fit the training photos would sit."""
    return torch.cat([first_hits(view, ground_z).points for view in scene.train])


def rule_steps(points: torch.Tensor, scene: Scene) -> dict:
    """The automatic rule's numbers on `points`: the focus, the nearest camera, the framing radius."""
    from matspray.geometry.region import REACH, framing_radius

    cameras = [v.camera for v in scene.train]
    focus = cameras_focus(cameras)
    nearest = min(float((c.center.double() - focus).norm()) for c in cameras)
    return {
        "focus": [round(v, 3) for v in focus.tolist()],
        "framing_radius": min(framing_radius(cameras, focus), REACH * nearest),
    }


def run_one(tabletop: str, seed: int, out: Path, args) -> dict:
    config = one_sided_config(
        tabletop, seed, args.resolution, args.views, args.fill, cameras=args.cameras, shape=args.shape
    )
    data = make_capture(config, out / f"{args.cameras}-{args.fill}-{args.shape}-{tabletop}-{seed}")
    record = json.loads((data / "scene.json").read_text())
    scene = load_scene(data)
    ground_z = record["photos"]["ground"]["z"]
    points = cloud(scene, ground_z)
    row = {"capture": f"{tabletop} {seed} ({record['shape']})", "object_radius": record["cameras"]["bounding_radius"]}
    row.update(rule_steps(points, scene))
    for name, found_on in (("gaussians", points), ("sparse", points[::SPARSE_EVERY])):
        region = auto_region(found_on, torch.ones(len(found_on)), [v.camera for v in scene.train])
        row[name] = {"region": region.describe(), "radius": region.radius, **score(region, scene, ground_z)}
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tabletops", nargs="+", choices=(*TABLETOPS, "grey"), default=list(TABLETOPS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/one-sided"))
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--fill", type=float, default=1.1)
    parser.add_argument("--cameras", choices=("front", "sphere", "turntable"), default="front")
    parser.add_argument("--shape", default="random")
    args = parser.parse_args()
    print("| capture | found on | region radius (framing / object) | object held | table held | IoU mean / min |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    for tabletop in args.tabletops:
        for seed in args.seeds:
            row = run_one(tabletop, seed, args.out, args)
            for name in ("gaussians", "sparse"):
                r = row[name]
                print(
                    f"| {row['capture']} | {name} | {r['radius']:.3f} ({row['framing_radius']:.3f} / "
                    f"{row['object_radius']:.3f}) | {r['object_held']:.1%} | {r['table_held']:.1%} | "
                    f"{r['iou_mean']:.3f} / {r['iou_min']:.3f} |"
                )
            print(f"<!-- {row['capture']}: {row['gaussians']['region']} -->")


if __name__ == "__main__":
    main()
