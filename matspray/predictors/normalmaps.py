"""Normal maps of the 2D prior: their convention, their checks and their conversions (pure functions).

The one internal convention (every `MaterialMaps.normals`, every `{view}_normal.exr` MatSpray writes):
- a normal map is [H, W, 3] float32 holding a unit vector where the source gives a normal and exactly
  (0, 0, 0) where it gives none (background). Zero is the only "no normal" value, so resampling and masking
  need no extra channel; `matspray synth` stores its true normals the same way.
- space "world": the scene's world frame (what `matspray synth` stores and the Gaussians carry).
- space "camera": the axes of the view's own camera in the OpenCV convention (docs/dev/architecture.md): x right,
  y down, z forward (from the camera into the scene). A surface the camera sees faces it, so its normal has z < 0.
  With R = viewmat[:3, :3] (the world-to-camera rotation), n_camera = R n_world and n_world = R^T n_camera.
Normal-estimation models such as Marigold use an OpenGL-style camera frame instead (x right, y up, z towards
the viewer); `from_opengl_camera` turns such normals into ours by negating y and z.
"""

from __future__ import annotations

import torch
from torch import Tensor

from matspray.data.camera import Camera

NORMAL_SPACES = ("camera", "world")
UNIT_TOLERANCE = 0.02  # |length - 1| allowed for a defined normal: 8-bit PNG quantisation moves it by at most 0.007
ZERO_LENGTH = 0.05  # vectors this short are "no normal" (averaging across the object's edge shortens them)
OPENGL_CAMERA_FLIP = (1.0, -1.0, -1.0)  # (x right, y up, z to viewer) <-> (x right, y down, z forward)


def defined(normals: Tensor) -> Tensor:  # [H, W, 3] -> [H, W] bool: the pixels that hold a normal
    return normals.norm(dim=-1) > ZERO_LENGTH


def normal_problem(normals: Tensor) -> str | None:
    """What makes `normals` no normal map (wrong shape, NaN/Inf, vectors neither unit nor zero), or None.
    Phrased to follow a file or view name: "<where> <problem>"."""
    if normals.ndim != 3 or normals.shape[-1] != 3:
        return f"must be [H, W, 3] (x, y, z per pixel), got shape {tuple(normals.shape)}"
    if not torch.isfinite(normals).all():
        return "holds NaN or Inf values"
    length = normals.float().norm(dim=-1)  # [H, W]
    bad = (length > ZERO_LENGTH) & ((length - 1.0).abs() > UNIT_TOLERANCE)
    if bad.any():
        count, total = int(bad.sum()), int((length > ZERO_LENGTH).sum())
        low, high = float(length[bad].min()), float(length[bad].max())
        return (
            f"holds vectors that are not unit length: {count} of {total} pixels have lengths from {low:.3g} to "
            f"{high:.3g} (a normal is a unit vector, or (0, 0, 0) where there is none)"
        )
    return None


def renormalised(normals: Tensor) -> Tensor:  # [H, W, 3] -> [H, W, 3] unit where defined, exactly 0 elsewhere
    length = normals.norm(dim=-1, keepdim=True)  # [H, W, 1]
    return torch.where(length > ZERO_LENGTH, normals / length.clamp_min(ZERO_LENGTH), torch.zeros_like(normals))


def camera_to_world(normals: Tensor, camera: Camera) -> Tensor:  # [H, W, 3] camera axes -> [H, W, 3] world
    R = camera.viewmat[:3, :3].to(normals)  # world -> camera
    return normals @ R  # row vectors: (R^T n)^T = n^T R; zero stays zero


def world_to_camera(normals: Tensor, camera: Camera) -> Tensor:  # [H, W, 3] world -> [H, W, 3] camera axes
    R = camera.viewmat[:3, :3].to(normals)
    return normals @ R.T


def from_opengl_camera(normals: Tensor) -> Tensor:  # [..., 3] (x right, y up, z to viewer) -> ours (OpenCV)
    return normals * torch.tensor(OPENGL_CAMERA_FLIP, dtype=normals.dtype, device=normals.device)


def facing_counts(normals: Tensor, directions: Tensor) -> tuple[int, int]:
    """How many defined normals of a map face its camera, and how many are defined: `normals` [H, W, 3] and the
    pixels' rays `directions` [H, W, 3] (Camera.pixel_directions) in one space. A surface a camera sees faces it
    (n . d < 0), so nearly all normals of a map read in its own space do; read in another space, about half or
    almost none do, which is how `FilesPredictor` tells a folder's space from what it says."""
    where = defined(normals)
    facing = ((normals * directions).sum(-1) < 0) & where
    return int(facing.sum()), int(where.sum())


def decode_png_normals(stored: Tensor) -> Tensor:  # [H, W, 3 or 4] in [0, 1] -> [H, W, 3] raw vectors
    """Normals stored for display as n * 0.5 + 0.5. Pixels stored black (0, 0, 0), as many tools leave the
    background, or with alpha 0 hold no normal and come out (0, 0, 0)."""
    rgb = stored[..., :3]
    vectors = rgb * 2.0 - 1.0
    empty = (rgb == 0).all(dim=-1)  # [H, W]
    if stored.shape[-1] == 4:
        empty = empty | (stored[..., 3] == 0)
    return torch.where(empty[..., None], torch.zeros_like(vectors), vectors)


def encode_png_normals(normals: Tensor) -> Tensor:  # [H, W, 3] unit or zero -> [H, W, 3] in [0, 1]
    return (normals * 0.5 + 0.5).clamp(0.0, 1.0)


def angular_error_deg(pred: Tensor, truth: Tensor) -> Tensor:  # [..., 3], [..., 3] unit -> [...] degrees
    cos = (renormalised(pred) * renormalised(truth)).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def mean_angular_error_deg(pred: Tensor, truth: Tensor, mask: Tensor | None = None) -> float:
    """Mean angle (degrees) between `pred` and `truth` [H, W, 3] over the pixels where both hold a normal
    (and `mask` [H, W] bool, when given); NaN when there are none."""
    where = defined(pred) & defined(truth)
    if mask is not None:
        where = where & mask.to(where.device)
    if not where.any():
        return float("nan")
    return float(angular_error_deg(pred, truth)[where].mean())
