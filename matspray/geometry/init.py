"""Initial Gaussians: COLMAP (or triangulated) points when the scene has them (topped up with scattered points
when a capture without masks has only a few); with masks, points on the visual hull's
surface (the first point along a ray through an object pixel that every mask calls object), coloured
by that pixel; otherwise random points in the object bounds plus, for the background of a capture
without masks, a shell of points far beyond the cameras (BACKGROUND_SHARE of them)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from matspray.data.images import linear_to_srgb
from matspray.data.scene import MIN_COLMAP_POINTS, Scene, View, focus_point
from matspray.errors import DataError
from matspray.gaussians import Gaussians
from matspray.render.shade.sh import num_sh_bases, rgb_to_sh_dc

BACKGROUND_SHARE = 0.25  # of the initial points of a capture without masks or points: on the background shell
SPARSE_SHARE = 0.25  # an unmasked capture with fewer points than this share of the count gets the rest scattered
BACKGROUND_RADIUS = 3.0  # the shell's radius, in farthest-camera distances from the focus


def initial_gaussians(
    scene: Scene,
    views: list[View],
    count: int,
    sh_degree: int,
    opacity: float,
    generator: torch.Generator,
    scale: float = 1.0,
    start: str = "hull",
) -> Gaussians:
    """`count` isotropic Gaussians (fewer with COLMAP points or thin masks), `scale` times the RMS
    distance to their 3 nearest neighbours, coloured by the sRGB colour they project to. A masked scene without points
    starts on its visual hull, or (`start="random"`, the paper's) anywhere in its bounds. They are made on the views'
    device; random draws come from the CPU `generator` (the same points on every device)."""
    device = views[0].image.device
    masked = any(v.alpha is not None for v in views)
    if scene.points is not None and len(scene.points) >= MIN_COLMAP_POINTS:
        points = scene.points.float()
        if len(points) > count:
            points = points[torch.randperm(len(points), generator=generator, device="cpu")[:count]]
        points = points.to(device)
        if not masked and len(points) < SPARSE_SHARE * count:
            # a few points (a weakly textured object's triangulation) leave most of the object without a Gaussian
            # to start from: the rest are scattered as without points
            points = torch.cat([points, scattered_points(scene, views, count - len(points), generator)])
        colours = projected_colours(points, views)
    elif masked and start == "hull":
        points, colours = hull_surface_points(scene.bounds.float().to(device), views, count, generator)
    elif masked:  # the paper's start: the object's box, filled uniformly (no background to cover)
        points = uniform_points(scene.bounds.float().to(device), count, generator)
        colours = projected_colours(points, views)
    else:
        points = scattered_points(scene, views, count, generator)
        colours = projected_colours(points, views)
    sh = torch.zeros(len(points), num_sh_bases(sh_degree), 3, device=device)
    sh[:, 0] = rgb_to_sh_dc(colours)
    quats = torch.zeros(len(points), 4, device=device)
    quats[:, 0] = 1.0
    return Gaussians(
        means=points,
        log_scales=torch.log(scale * neighbour_spacing(points))[:, None].repeat(1, 3),
        quats=quats,
        opacity_logits=torch.full(
            (len(points),), float(torch.logit(torch.tensor(opacity, device="cpu"))), device=device
        ),
        sh=sh,
    )


def scattered_points(scene: Scene, views: list[View], count: int, generator: torch.Generator) -> Tensor:  # [count, 3]
    """Random points in the scene's bounds and, for the background of a capture without masks, BACKGROUND_SHARE of
    them on a far shell."""
    device = views[0].image.device
    shell = int(BACKGROUND_SHARE * count)
    inner = uniform_points(scene.bounds.float().to(device), count - shell, generator)
    return torch.cat([inner, background_shell(views, shell).to(device)])


def uniform_points(bounds: Tensor, count: int, generator: torch.Generator) -> Tensor:  # [2, 3] -> [count, 3]
    """`count` points drawn uniformly in the box `bounds` (min and max corners), from the CPU `generator`."""
    return bounds[0] + (bounds[1] - bounds[0]) * torch.rand(count, 3, generator=generator).to(bounds.device)


def hull_surface_points(
    bounds: Tensor, views: list[View], count: int, generator: torch.Generator, samples_per_ray: int = 128
) -> tuple[Tensor, Tensor]:
    """About `count` points [P, 3] on the visual hull of the masked views, with sRGB colours [P, 3].

    Rays through random object pixels (alpha > 0.5) of every masked view are sampled across the
    bounds [2, 3]; the first sample inside every mask that sees it is the hull's surface, as seen
    from that view."""
    masked = [v for v in views if v.alpha is not None]
    per_view = -(-count // len(masked))
    points, colours = [], []
    for view in masked:
        weights = (view.alpha.reshape(-1) > 0.5).float().cpu()  # drawn on the CPU: the same picks on every device
        if float(weights.sum()) == 0:
            continue
        picks = torch.multinomial(weights, per_view, replacement=True, generator=generator)
        jitter = torch.rand(per_view, 2, generator=generator, device="cpu")
        pixels = (
            torch.stack([picks % view.width, torch.div(picks, view.width, rounding_mode="floor")], -1).float() + jitter
        ).to(bounds.device)
        origins, dirs = view.camera.rays_through(pixels)
        near, far = box_entry_exit(origins, dirs, bounds)
        steps = (torch.arange(samples_per_ray, device=bounds.device) + 0.5) / samples_per_ray
        t = near[:, None] + (far - near)[:, None] * steps  # [R, S]
        samples = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
        inside = torch.ones(len(samples), dtype=torch.bool, device=samples.device)
        for other in masked:
            values, seen = sample_image(other.alpha[..., None], other, samples)
            inside &= ~seen | (values[:, 0] > 0.5)
        inside = inside.reshape(per_view, samples_per_ray) & (far > near)[:, None]
        hit = inside.any(dim=1)
        first = torch.argmax(inside.int(), dim=1)
        rays = torch.nonzero(hit).squeeze(1)
        points.append(origins[rays] + t[rays, first[rays], None] * dirs[rays])
        colours.append(linear_to_srgb(view.image)[pixels[rays, 1].long(), pixels[rays, 0].long()])
    points = torch.cat(points) if points else torch.zeros(0, 3, device=bounds.device)
    if len(points) < max(1, count // 100):
        raise DataError(
            f"the masks leave only {len(points)} initial points on the object "
            "(check that the masks, i.e. the alpha channels, show the object and that the cameras are "
            "right: matspray info)"
        )
    return points, torch.cat(colours)


def background_shell(views: list[View], count: int) -> Tensor:  # -> [count, 3]
    """`count` points evenly spread (Fibonacci) on a sphere around the cameras' focus, BACKGROUND_RADIUS times
    the farthest camera's distance: where a capture's far background (sky, walls) can start from."""
    if count <= 0:
        return torch.zeros(0, 3)
    focus = focus_point(views)
    radius = BACKGROUND_RADIUS * max(float((v.camera.center.double().cpu() - focus).norm()) for v in views)
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    ring = (1.0 - z**2).clamp_min(0).sqrt()
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * k
    directions = torch.stack([ring * torch.cos(azimuth), ring * torch.sin(azimuth), z], dim=-1)
    return (focus + radius * directions).float()


def box_entry_exit(origins: Tensor, dirs: Tensor, bounds: Tensor) -> tuple[Tensor, Tensor]:  # -> [R], [R]
    """Ray parameters where rays enter and leave the box [2, 3] (far < near when they miss it)."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0, t1 = (bounds[0] - origins) / safe, (bounds[1] - origins) / safe
    near = torch.minimum(t0, t1).max(dim=-1).values.clamp_min(0)
    far = torch.maximum(t0, t1).min(dim=-1).values
    return near, far


def sample_image(image: Tensor, view: View, points: Tensor) -> tuple[Tensor, Tensor]:
    """Nearest-pixel values [P, C] of `image` [H, W, C] at the projections of `points` [P, 3], and
    whether each point lies in front of the camera and inside the image [P]."""
    pixels, depth = view.camera.project(points)
    cols, rows = pixels[:, 0].floor().long(), pixels[:, 1].floor().long()
    seen = (depth > 0) & (cols >= 0) & (cols < view.width) & (rows >= 0) & (rows < view.height)
    values = image[rows.clamp(0, view.height - 1), cols.clamp(0, view.width - 1)]
    return values, seen


def projected_colours(points: Tensor, views: list[View]) -> Tensor:  # [P, 3] -> [P, 3] sRGB
    """Mean sRGB colour at each point's projection over the views where it lands on the object."""
    total, weight = torch.zeros(len(points), 3, device=points.device), torch.zeros(len(points), 1, device=points.device)
    for view in views:
        colours, seen = sample_image(linear_to_srgb(view.image), view, points)
        w = seen.float()[:, None]
        if view.alpha is not None:
            w = w * sample_image(view.alpha[..., None], view, points)[0]
        total += colours * w
        weight += w
    return torch.where(weight > 0, total / weight.clamp_min(1e-8), torch.full_like(total, 0.5))


def neighbour_spacing(points: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:  # [P, 3] -> [P]
    """Root mean squared distance to the k nearest other points (3DGS's initial scale)."""
    out = torch.empty(len(points), device=points.device)
    k = min(k, max(1, len(points) - 1))
    for start in range(0, len(points), chunk):
        d2 = torch.cdist(points[start : start + chunk], points).square()
        rows = torch.arange(d2.shape[0], device=points.device)
        d2[rows, rows + start] = float("inf")
        nearest = torch.topk(d2, k, dim=1, largest=False).values
        out[start : start + chunk] = nearest.mean(dim=1).sqrt()
    return out.clamp_min(1e-7)
