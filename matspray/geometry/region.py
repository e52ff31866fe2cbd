"""The object in a capture without masks: the region of space that holds it, and its masks.

Geometry is fitted to the whole capture (background included). The object is then the Gaussians
inside an object region, and their rendered alpha becomes every view's mask. The region is a sphere
or a box, given (`--object-bounds`) or chosen automatically by this rule:

  1. Centre: the point every camera's optical axis passes closest to (what the cameras look at).
  2. Candidates: the opaque Gaussians (opacity >= 0.5) within 0.9 x the nearest camera's distance of it.
  3. Support plane: a plane (RANSAC over the candidates) holding >= 20% of them within 2% of that
     distance, with every camera on one side and a quarter of those points beyond half that distance
     from the centre (it reaches past the framed object, so it is no face of the object), is the
     ground or table: the region is cut 4% of that distance above it.
  4. Radius: at most the framing radius, the largest sphere around the centre that every camera sees
     whole (an object-centred capture frames its object); within it, the candidates left are binned by
     distance from the centre, and outward from the densest shell the region ends at the first shell
     whose density (Gaussians per volume) falls below 10% of that shell's, plus 5% (the densest shell among those
     holding at least 1% of the candidates).
  5. Growth, on a table only (step 3 found one): the radius grows to hold, plus 5%, the candidates above the
     table's cut that are connected to those inside it (through voxels of a 16th of the radius, each touching the
     next), out to at most 1.6 times that radius. An object that fills the frame, or one seen from one side,
     reaches past the framing sphere (a skull's back was cut off); what rests on the table beside it and
     touches it is held with it; the room, apart from it, is not. Without a table the growth is not made: it would
     run along the ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from matspray.data.camera import Camera
from matspray.data.scene import cameras_focus
from matspray.errors import SettingError

MIN_OPACITY = 0.5  # candidates of the automatic rule
REACH = 0.9  # candidates lie within this fraction of the nearest camera's distance
PLANE_TOLERANCE, PLANE_SHARE, PLANE_MARGIN = 0.02, 0.1, 0.04  # fractions of that distance (share: of the candidates)
PLANE_TRIALS = 256
PLANE_BELOW = 0.05  # a table past the framing sphere has at most this share of the candidates below it
PLANE_REACH, PLANE_REACH_SHARE = (
    0.5,
    0.25,
)  # a ground's points reach this far (fraction of that distance), this many of them
SHELLS, DENSITY_FLOOR, RADIUS_MARGIN = 48, 0.1, 1.05
PEAK_SHARE = 0.01  # the densest shell is chosen among those holding at least this share of the candidates
GROW_CELLS, GROW_LIMIT = 16, 1.6  # step 5's voxels per radius, and how far it may grow (times the radius)


@dataclass(frozen=True)
class ObjectRegion:
    """A sphere (`radius`) or a box (`low`, `high`) around `center`, optionally cut by a support plane:
    points p with dot(plane[:3], p) + plane[3] < 0 are outside."""

    center: tuple[float, float, float]
    radius: float | None = None
    low: tuple[float, float, float] | None = None
    high: tuple[float, float, float] | None = None
    plane: tuple[float, float, float, float] | None = None
    rule: str = "given"  # 'given' (--object-bounds) or 'auto'

    def contains(self, points: Tensor) -> Tensor:  # [N, 3] -> [N] bool
        points = points.double()
        if self.radius is not None:
            inside = (points - points.new_tensor(self.center)).norm(dim=-1) <= self.radius
        else:
            inside = ((points >= points.new_tensor(self.low)) & (points <= points.new_tensor(self.high))).all(-1)
        if self.plane is not None:
            plane = points.new_tensor(self.plane)
            inside &= points @ plane[:3] + plane[3] >= 0
        return inside

    def bounds(self) -> Tensor:  # [2, 3] axis-aligned box around the region
        if self.radius is not None:
            center = torch.tensor(self.center, dtype=torch.float32)
            return torch.stack([center - self.radius, center + self.radius])
        return torch.tensor([self.low, self.high], dtype=torch.float32)

    def describe(self) -> str:
        shape = (
            f"sphere at ({', '.join(f'{v:.3f}' for v in self.center)}) of radius {self.radius:.3f}"
            if self.radius is not None
            else f"box ({', '.join(f'{v:.3f}' for v in self.low)}) .. ({', '.join(f'{v:.3f}' for v in self.high)})"
        )
        cut = (
            ""
            if self.plane is None
            else f", cut above the plane {' '.join(f'{v:+.3f}' for v in self.plane)} (n.x + d >= 0)"
        )
        return f"{shape}{cut} ({'chosen automatically' if self.rule == 'auto' else 'given'})"

    def to_json(self) -> dict:
        return {
            "center": list(self.center),
            "radius": self.radius,
            "low": None if self.low is None else list(self.low),
            "high": None if self.high is None else list(self.high),
            "plane": None if self.plane is None else list(self.plane),
            "rule": self.rule,
        }

    @staticmethod
    def from_json(data: dict) -> "ObjectRegion":
        as_tuple = lambda v: None if v is None else tuple(float(x) for x in v)  # noqa: E731
        return ObjectRegion(
            center=as_tuple(data["center"]),
            radius=data.get("radius"),
            low=as_tuple(data.get("low")),
            high=as_tuple(data.get("high")),
            plane=as_tuple(data.get("plane")),
            rule=data.get("rule", "given"),
        )


def given_region(values) -> ObjectRegion:
    """`--object-bounds`: 4 numbers (x y z radius) for a sphere or 6 (x0 y0 z0 x1 y1 z1) for a box."""
    values = [float(v) for v in values]
    if not all(math.isfinite(v) for v in values):
        raise SettingError("object_bounds", f"must be finite numbers, got {values}")
    if len(values) == 4:
        if values[3] <= 0:
            raise SettingError("object_bounds", f"the sphere's radius must be > 0, got {values[3]}")
        return ObjectRegion(center=tuple(values[:3]), radius=values[3])
    if len(values) == 6:
        low, high = tuple(values[:3]), tuple(values[3:])
        if not all(lo < hi for lo, hi in zip(low, high)):
            raise SettingError(
                "object_bounds", f"the box's first corner must be below its second on every axis, got {values}"
            )
        return ObjectRegion(center=tuple((lo + hi) / 2 for lo, hi in zip(low, high)), low=low, high=high)
    raise SettingError(
        "object_bounds", f"give 4 numbers (x y z radius: a sphere) or 6 (x0 y0 z0 x1 y1 z1: a box), got {len(values)}"
    )


def support_plane(
    points: Tensor,
    camera_centers: Tensor,
    tolerance: float,
    generator: torch.Generator,
    far: Tensor | None = None,
    framed: Tensor | None = None,
) -> Tensor | None:
    """RANSAC plane [4] (unit normal n, offset d; cameras on the side n.x + d > 0) holding >= PLANE_SHARE of
    `points` [P, 3] within `tolerance`, PLANE_REACH_SHARE of them among the `far` ones ([P] bool; None: any), or
    as many among those past the framing sphere (`framed`, [P] bool) with at most PLANE_BELOW of the points below it
    (away from the cameras), or None. The second way finds the table of an object that fills the frame (none of
    the table it shows is far); the object's own face that the cameras look at has the object behind it."""
    count = len(points)
    if count < 3:
        return None
    reaches = lambda on_plane, among: int((on_plane & among).sum()) >= PLANE_REACH_SHARE * int(on_plane.sum())  # noqa: E731
    best, best_inliers = None, int(PLANE_SHARE * count) - 1
    for _ in range(PLANE_TRIALS):
        a, b, c = points[torch.randint(count, (3,), generator=generator)]
        normal = torch.linalg.cross(b - a, c - a)
        if normal.norm() < 1e-12:
            continue
        normal = normal / normal.norm()
        offset = -(normal @ a)
        side = camera_centers @ normal + offset
        if not ((side > tolerance).all() or (side < -tolerance).all()):
            continue  # a ground or table has every camera on one side
        sign = 1.0 if float(side[0]) > 0 else -1.0
        height = sign * (points @ normal + offset)  # [P] above the plane, on the cameras' side
        on_plane = height.abs() <= tolerance
        inliers = int(on_plane.sum())
        if inliers <= best_inliers:
            continue
        supports = lambda: float((height < -tolerance).double().mean()) <= PLANE_BELOW  # noqa: E731
        if far is None or reaches(on_plane, far) or (framed is not None and reaches(on_plane, framed) and supports()):
            best, best_inliers = torch.cat([sign * normal, (sign * offset).reshape(1)]), inliers
    return best


def dense_radius(distances: Tensor, reach: float) -> float:
    """Where the density of points at `distances` [P] (from the centre) falls, outward from its densest
    shell, below DENSITY_FLOOR of that shell's density: the dense core's radius (rule step 4). Surfaces
    leave the inside of an object empty, so the scan starts at the densest shell, not at the centre."""
    edges = torch.linspace(0.0, reach, SHELLS + 1, dtype=torch.float64)
    counts = torch.histogram(distances.double().clamp(max=reach), bins=edges).hist
    counts[-1] -= int((distances >= reach).sum())  # points beyond reach are not in the last shell
    density = counts / (edges[1:] ** 3 - edges[:-1] ** 3)
    # the peak is a shell that holds a share of the points: the innermost shells are so small that one stray point
    # there would outweigh the object's surface and end the region at a fraction of the object
    populated = counts >= max(1.0, PEAK_SHARE * float(counts.sum()))
    peak = int(torch.where(populated, density, torch.zeros_like(density)).argmax())
    for shell in range(peak + 1, SHELLS):
        if density[shell] < DENSITY_FLOOR * density[peak]:
            return float(edges[shell]) * RADIUS_MARGIN
    return reach


def grown_radius(distances: Tensor, points: Tensor, focus: Tensor, radius: float) -> float:
    """Rule step 5: the radius that holds the `points` [P, 3] (at `distances` [P] from `focus` [3]) connected to those
    within `radius`, through voxels of radius / GROW_CELLS that touch (faces, edges or corners), out to GROW_LIMIT
    times `radius`; at least `radius`."""
    from scipy import ndimage

    limit = GROW_LIMIT * radius
    near = distances <= limit
    if not bool((distances <= radius).any()):
        return radius
    side = radius / GROW_CELLS
    cells = ((points[near] - focus + limit) / side).floor().long().clamp(min=0)  # [Q, 3]
    shape = [int(cells.max()) + 1] * 3
    occupied = torch.zeros(shape, dtype=torch.bool)
    occupied[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    labels, _ = ndimage.label(occupied.numpy(), structure=torch.ones(3, 3, 3).numpy())
    labels = torch.from_numpy(labels)[cells[:, 0], cells[:, 1], cells[:, 2]]  # [Q] each point's component
    held = torch.zeros(int(labels.max()) + 1, dtype=torch.bool)
    held[labels[distances[near] <= radius]] = True
    reached = float(distances[near][held[labels]].max()) * RADIUS_MARGIN
    return min(max(radius, reached), limit)


def framing_radius(cameras: list[Camera], focus: Tensor) -> float:
    """The radius of the largest sphere around `focus` [3] inside every camera's field of view (centred
    principal point assumed: the narrower half-angle of each camera)."""
    radii = []
    for camera in cameras:
        K = camera.K.double().cpu()
        half = min(math.atan(0.5 * camera.width / float(K[0, 0])), math.atan(0.5 * camera.height / float(K[1, 1])))
        radii.append(float((camera.center.double().cpu() - focus).norm()) * math.sin(half))
    return min(radii)


def opaque_near(means: Tensor, opacities: Tensor, focus: Tensor, nearest: float) -> Tensor:  # -> [C, 3] float64
    """Rule step 2's candidates: the opaque Gaussians within REACH x `nearest` of `focus` (all near ones when fewer
    than 8 are opaque)."""
    points = means.detach().double().cpu()
    near = (points - focus).norm(dim=-1) <= REACH * nearest
    candidates = points[near & (opacities.detach().cpu() >= MIN_OPACITY)]
    return candidates if len(candidates) >= 8 else points[near]


def nearest_distance(cameras: list[Camera], focus: Tensor) -> float:
    return float((torch.stack([c.center.double().cpu() for c in cameras]) - focus).norm(dim=-1).min())


def auto_region(means: Tensor, opacities: Tensor, cameras: list[Camera], seed: int = 0) -> ObjectRegion:
    """The object region of Gaussians (means [N, 3], opacities [N]) seen by `cameras`, by the module's rule."""
    centers = torch.stack([c.center.double().cpu() for c in cameras])
    focus = cameras_focus(cameras)
    nearest = nearest_distance(cameras, focus)
    candidates = opaque_near(means, opacities, focus, nearest)
    generator = torch.Generator().manual_seed(seed)
    framed = min(framing_radius(cameras, focus), REACH * nearest)
    distances = (candidates - focus).norm(dim=-1)
    plane = support_plane(
        candidates, centers, PLANE_TOLERANCE * nearest, generator, distances > PLANE_REACH * nearest, distances > framed
    )
    if plane is not None:
        plane = plane.clone()
        plane[3] -= PLANE_MARGIN * nearest  # the region starts a margin above the plane
        candidates = candidates[candidates @ plane[:3] + plane[3] >= 0]
    distances = (candidates - focus).norm(dim=-1)
    radius = dense_radius(distances, framed) if len(candidates) else framed
    if plane is not None and len(candidates):  # the candidates are those above the table's cut
        radius = grown_radius(distances, candidates, focus, radius)
    return ObjectRegion(
        center=tuple(focus.tolist()), radius=radius, plane=None if plane is None else tuple(plane.tolist()), rule="auto"
    )


def regrown(region: ObjectRegion, means: Tensor, opacities: Tensor, cameras: list[Camera]) -> ObjectRegion:
    """An automatic region on a table found before the geometry knew the object (on the sparse points the photos
    were cut by, or on the Gaussians at the focus), grown (rule step 5) over the trained Gaussians (means [N, 3],
    opacities [N]): the parts of the object that were thin then are held now. It only grows; a given region, a box
    or one without a table is returned as it is."""
    if region.rule != "auto" or region.plane is None or region.radius is None:
        return region
    focus = torch.tensor(region.center, dtype=torch.float64)
    candidates = opaque_near(means, opacities, focus, nearest_distance(cameras, focus))
    plane = torch.tensor(region.plane, dtype=torch.float64)
    candidates = candidates[candidates @ plane[:3] + plane[3] >= 0]
    if not len(candidates):
        return region
    radius = grown_radius((candidates - focus).norm(dim=-1), candidates, focus, region.radius)
    return replace(region, radius=radius)


def object_region(means: Tensor, opacities: Tensor, cameras: list[Camera], object_bounds=None) -> ObjectRegion:
    """The region `object_bounds` gives (`given_region`'s numbers), else the automatic rule's on these Gaussians."""
    if object_bounds is not None:
        return given_region(object_bounds)
    return auto_region(means, opacities, cameras)


def mask_iou(
    mask: Tensor, truth: Tensor, threshold: float = 0.5
) -> float:  # [H, W], [H, W] -> IoU of the thresholded masks
    a, b = mask >= threshold, truth >= threshold
    union = int((a | b).sum())
    return 1.0 if union == 0 else int((a & b).sum()) / union
