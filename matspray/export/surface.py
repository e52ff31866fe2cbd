"""A closed surface from the Gaussians: TSDF fusion of the depth and coverage the asset renders at the
training cameras, marching cubes (scikit-image) on the fused field, and the object kept (largest
connected components, no floaters; trimesh).

Why this way: the rasterizer already gives depth and coverage per view, so fusing them is a few tensor
operations on a voxel grid (no extra heavy dependency such as Open3D, ~0.5 GB), the coverage carves
free space exactly where the asset is transparent, and marching cubes on a field padded with free space
always yields a closed mesh, so there are no holes to close afterwards but the ones cleanup makes."""

from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy.ndimage import distance_transform_edt, label
from skimage.measure import marching_cubes
from torch import Tensor
from tqdm import tqdm

from matspray.data.camera import Camera
from matspray.errors import DataError
from matspray.export.bake import sample_bilinear
from matspray.export.silhouette import silhouette_offset
from matspray.gaussians import Gaussians
from matspray.render.raster.rasterize import rasterize

CALIBRATION_STEPS = 2  # rounds of moving the surface's level to match the asset's silhouettes
# A smooth metal shows a mirror image, and the Gaussians that reproduce it sit where the reflected scene
# appears, behind the surface (for a convex mirror, up to half its radius of curvature deep), so their depth
# carves pits into the object. A pixel counts as a mirror by its rendered metallic and roughness, ramped
# between these bounds (perceptual roughness: GGX alpha = r^2, so 0.45 already blurs a reflection a lot).
MIRROR_METALLIC = (0.5, 0.8)
MIRROR_ROUGHNESS = (0.45, 0.25)
# Those pits are what the plain TSDF cannot refuse: a view that sees a voxel deeper than the truncation behind
# the surface casts no vote, so the one view whose depth runs deep decides alone. A voxel that at least this
# share of the views seeing it (in front of or deep behind their surface) sees hidden is inside; a real
# concavity is seen from fewer directions, so a share close to 1 keeps most of those open.
OCCLUDED_SHARE = 0.95


def render_views(
    gaussians: Gaussians, cameras: list[Camera], materials: Tensor | None = None, progress: bool = False
) -> tuple[list[tuple[Tensor, Tensor]], list[Tensor] | None]:
    """Per camera, coverage-weighted depth [H, W] (sum_k w_k z_k, see `RasterOutput.depth`) and coverage alpha
    [H, W]; with the Gaussians' `materials` [N, 5], also each pixel's `depth_trust` [H, W], from the same
    rasterization (roughness and metallic as its colour), else None."""
    colours = (
        materials[:, 3:5].to(gaussians.device)
        if materials is not None
        else torch.ones(len(gaussians), 1, device=gaussians.device)
    )
    depths, trust = [], []
    with torch.no_grad():
        for camera in tqdm(cameras, desc="export: depth", disable=not progress, dynamic_ncols=True):
            raster = rasterize(gaussians, camera.to(colours.device), colours)
            depths.append((raster.depth.cpu(), raster.alpha.cpu()))  # the TSDF fuses on the CPU
            if materials is not None:
                rough, metal = (raster.features / raster.alpha.clamp_min(1e-6)[..., None]).cpu().unbind(-1)
                trust.append(mirror_trust(rough, metal))
    return depths, trust if materials is not None else None


def render_depths(gaussians: Gaussians, cameras: list[Camera], progress: bool = False) -> list[tuple[Tensor, Tensor]]:
    """Depth and alpha of the Gaussians at each camera (`render_views`)."""
    return render_views(gaussians, cameras, progress=progress)[0]


def ramp(x: Tensor, start: float, end: float) -> Tensor:  # 0 at start, 1 at end (either order), linear between
    return ((x - start) / (end - start)).clamp(0.0, 1.0)


def mirror_trust(roughness: Tensor, metallic: Tensor) -> Tensor:
    """How far a pixel's rendered depth is the depth of the surface: 1 for rough or dielectric material,
    falling to 0 on smooth metal, whose depth is that of its reflection (see MIRROR_METALLIC)."""
    return 1.0 - ramp(metallic, *MIRROR_METALLIC) * ramp(roughness, *MIRROR_ROUGHNESS)


def depth_trust(
    gaussians: Gaussians, materials: Tensor, cameras: list[Camera]
) -> list[Tensor]:  # materials [N, 5] -> [H, W] each
    """`mirror_trust` of the pixels the Gaussians render at each camera."""
    return render_views(gaussians, cameras, materials)[1]


def object_box(gaussians: Gaussians, min_opacity: float = 0.05) -> Tensor:  # -> [2, 3] min, max of the visible centres
    keep = gaussians.opacities > min_opacity
    means = gaussians.means[keep] if keep.any() else gaussians.means
    if len(means) == 0:
        raise DataError("the asset has no Gaussians to make a surface from")
    return torch.stack([means.min(0).values, means.max(0).values])


def voxel_grid(box: Tensor, grid: int, margin: float = 0.05) -> tuple[Tensor, float, tuple[int, int, int]]:
    """Voxel centres [X * Y * Z, 3] covering `box` [2, 3] plus a margin; the voxel size; the grid shape."""
    size = (box[1] - box[0]).clamp_min(1e-6)
    lo, hi = box[0] - margin * size.max(), box[1] + margin * size.max()
    voxel = float((hi - lo).max()) / grid
    shape = tuple(int(n) + 1 for n in torch.ceil((hi - lo) / voxel).tolist())
    axes = [lo[i] + voxel * torch.arange(shape[i], dtype=torch.float32) for i in range(3)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return centres, voxel, shape


def silhouette_gap(alpha: Tensor, min_alpha: float) -> Tensor:  # [H, W] -> [H, W] float32, pixels
    """How far each empty pixel's centre (alpha < min_alpha) lies outside the silhouette: the distance to
    the nearest covered pixel's centre less half a pixel (the edge between the two); 0 on covered pixels.
    A view with no covered pixel reports every pixel as far."""
    empty = (alpha < min_alpha).numpy()
    if empty.all():
        return torch.full(alpha.shape, float(max(alpha.shape)))
    distance = distance_transform_edt(empty)  # 0 on covered pixels
    return torch.from_numpy(np.maximum(distance - 0.5, 0.0).astype(np.float32))


def fuse_tsdf(
    centres: Tensor,  # [M, 3] voxel centres
    cameras: list[Camera],
    depths: list[tuple[Tensor, Tensor]],  # per camera: weighted depth [H, W], alpha [H, W] (`render_depths`)
    truncation: float,  # distance (world units) beyond which the field saturates
    min_alpha: float = 0.5,
    trust: list[Tensor] | None = None,  # per camera [H, W] in [0, 1]: weight of a covered pixel's depth (`depth_trust`)
    occluded_share: float = OCCLUDED_SHARE,
) -> tuple[Tensor, Tensor]:  # -> field [M] in [-1, 1] (> 0 outside, < 0 inside), unknown [M] bool
    """Truncated signed distance along each camera's z axis, averaged over the views that saw the voxel
    in front of the surface or through empty pixels (a covered pixel's vote weighted by its `trust`; an empty
    pixel's, the silhouette's, always counts in full). A voxel that at least `occluded_share` of the views which
    see it see deeper than the truncation behind the surface is inside (-1); one that lies that deep in every
    view that sees it is inside (-1) and unknown; a voxel no camera sees is outside (+1)."""
    total = torch.zeros(len(centres))
    weight = torch.zeros(len(centres))
    seen, hidden = (
        torch.zeros(len(centres)),
        torch.zeros(len(centres)),
    )  # views that see the voxel in front of / deep behind the surface
    in_view = torch.zeros(len(centres), dtype=torch.bool)
    for view, (camera, (depth, alpha)) in enumerate(zip(cameras, depths)):
        pixels, z = camera.project(centres)
        idx = camera.in_image(pixels, z).nonzero().squeeze(1)
        gap = silhouette_gap(alpha.cpu(), min_alpha)
        confidence = trust[view].cpu() if trust is not None else torch.ones_like(gap)
        weighted, cover, off, sure = sample_bilinear(
            torch.stack([depth.cpu(), alpha.cpu(), gap, confidence], dim=-1), pixels[idx]
        ).unbind(-1)
        covered = cover >= min_alpha
        sdf = (weighted / cover.clamp_min(1e-6) - z[idx]) / truncation
        # an empty pixel: free space all along the ray, but only as far from the surface as the ray passes
        # from the silhouette (pixels -> world at the voxel's depth). Saturating to +1 there instead let one
        # grazing view outvote the views that see the voxel just inside the surface, eroding the silhouette
        # by about a pixel all round (the mesh covered fewer pixels than the truth: docs/defaults.md)
        focal = 0.5 * float(camera.K[0, 0] + camera.K[1, 1])
        free = (off * z[idx] / focal / truncation).clamp(min=1e-3, max=1.0)
        sdf = torch.where(covered, sdf, free)
        vote = torch.where(covered, sure, torch.ones_like(sure))
        used = (sdf >= -1.0) & (
            vote > 1e-3
        )  # deeper than the truncation behind the surface, or a mirror: no information
        total.index_add_(0, idx[used], vote[used] * sdf[used].clamp(max=1.0))
        weight.index_add_(0, idx[used], vote[used])
        seen.index_add_(0, idx, torch.where(sdf > 0, vote, 0.0))
        hidden.index_add_(0, idx, torch.where(sdf < -1.0, vote, 0.0))
        in_view[idx] = True
    field = torch.where(weight > 0, total / weight.clamp_min(1e-12), -torch.ones_like(total))
    # nearly every view sees it hidden: inside, whatever the few others say (see OCCLUDED_SHARE)
    hides = (hidden >= occluded_share * (hidden + seen)) & (hidden > 0)
    field = torch.where(hides, -torch.ones_like(field), field)
    return torch.where(in_view, field, torch.ones_like(field)), in_view & (weight == 0)


def open_to_outside(field: Tensor, unknown: Tensor, shape: tuple[int, int, int]) -> Tensor:  # [M], [M] bool -> [M]
    """Unknown voxels (behind the surface in every view that sees them) that reach the grid's border
    through unknown voxels alone are outside: space that too few views carve would otherwise stay solid
    and close the grid with walls. Unknown space that observed surface or free space encloses stays inside."""
    grid = unknown.reshape(shape).numpy()
    labels, _ = label(
        np.pad(grid, 1, constant_values=True)
    )  # the padding joins the border's unknown voxels into one region
    outside = (labels == labels[0, 0, 0])[1:-1, 1:-1, 1:-1].reshape(-1)
    return torch.where(unknown & torch.from_numpy(outside), torch.ones_like(field), field)


def extract_surface(
    field: Tensor, shape: tuple[int, int, int], origin: Tensor, voxel: float, level: float = 0.0
) -> trimesh.Trimesh:
    """Marching cubes on the `level` set of `field` [X * Y * Z] (padded with free space, so the result is
    closed; level > 0 grows the surface outwards), faces wound counter-clockwise seen from outside."""
    volume = np.pad(field.reshape(shape).numpy().astype(np.float32), 1, constant_values=1.0)
    if volume.min() >= level or volume.max() <= level:
        raise DataError("the fused depth holds no surface (the asset renders empty or fills every view)")
    verts, faces, _, _ = marching_cubes(-volume, level=-level, spacing=(voxel, voxel, voxel))
    verts = verts - voxel + origin.numpy()[None].astype(np.float64)  # undo the padding
    mesh = trimesh.Trimesh(verts, faces[:, ::-1], process=True)
    if mesh.is_volume and mesh.volume < 0:
        mesh.invert()
    return mesh


def keep_object(mesh: trimesh.Trimesh, keep_fraction: float) -> trimesh.Trimesh:
    """The connected components with at least `keep_fraction` of the largest one's faces (floaters go),
    without cavities: closed components wound inwards (negative volume), which no outside view sees."""
    parts = [p for p in mesh.split(only_watertight=False) if not (p.is_watertight and p.volume < 0)]
    if not parts:
        return mesh
    largest = max(len(p.faces) for p in parts)
    kept = [p for p in parts if len(p.faces) >= keep_fraction * largest]
    return kept[0] if len(kept) == 1 else trimesh.util.concatenate(kept)


def fuse_surface(
    gaussians: Gaussians,
    cameras: list[Camera],
    grid: int,
    truncation_voxels: float,
    min_alpha: float,
    keep_fraction: float,
    progress: bool = False,
    calibrate: bool = True,
    materials: Tensor | None = None,
    region=None,
) -> tuple[trimesh.Trimesh, float, list[Tensor]]:
    """The whole step: depths -> TSDF on a grid around the Gaussians -> marching cubes -> the object, its
    level moved so its silhouettes cover what the asset's do (`calibrate`, `silhouette.silhouette_offset`); with the
    Gaussians' `materials` [N, 5], mirror-like pixels' depths are not trusted (`depth_trust`). Also returns the
    voxel size (the surface's resolution) and the asset's coverage [H, W] at each camera (on the CPU). `region`
    (an ObjectRegion: a capture's object region) bounds the surface: space outside it is free, so the unseen
    underside of an object on a table closes at the region's cut instead of reaching down into the table."""
    depths, trust = render_views(gaussians, cameras, materials, progress)
    centres, voxel, shape = voxel_grid(object_box(gaussians).cpu(), grid)
    field, unknown = fuse_tsdf(
        centres, [c.to("cpu") for c in cameras], depths, truncation_voxels * voxel, min_alpha, trust
    )
    field = open_to_outside(field, unknown, shape)
    if region is not None:
        field = torch.where(region.contains(centres.double()).to(field.device), field, torch.ones_like(field))
    mesh = extract_surface(field, shape, centres[0], voxel)
    level = 0.0
    for _ in range(CALIBRATION_STEPS if calibrate else 0):
        # the field is about a distance over the truncation near the surface (the average of projective distances
        # is steeper, so one step moves the rim only half way, hence a second): move its level by the offset the
        # silhouettes show, at most a voxel each step (a larger miss is not a depth bias but a wrong surface)
        offset = silhouette_offset(keep_object(mesh, keep_fraction), cameras, [alpha for _, alpha in depths], min_alpha)
        level += float(np.clip(offset, -voxel, voxel)) / (truncation_voxels * voxel)
        mesh = extract_surface(field, shape, centres[0], voxel, level)
    mesh = keep_object(mesh, keep_fraction)
    trimesh.repair.fill_holes(mesh)
    return mesh, voxel, [alpha for _, alpha in depths]
