"""Gaussians as PLY files in the standard 3DGS layout, so common 3DGS viewers open them.

One `vertex` element with float32 properties, in this order:
    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3 (K - 1) - 1)  opacity  scale_0..2  rot_0..3
f_rest is channel-major (f_rest_{c (K - 1) + k} is coefficient k + 1 of channel c), opacity is the
logit, scales are logs and rot is the quaternion (w, x, y, z), as 3DGS stores them. Standard files
carry zero normals; ours carry each Gaussian's oriented shortest-axis normal.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError
from torch import Tensor

from matspray.data.images import atomic_target
from matspray.errors import file_error
from matspray.gaussians import Gaussians
from matspray.rundir import stage_hint

REQUIRED = "x y z f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split()


def property_names(sh_bases: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (sh_bases - 1))]
    return [*REQUIRED[:3], "nx", "ny", "nz", *REQUIRED[3:6], *rest, *REQUIRED[6:]]  # 3DGS's order


def write_ply(
    path, gaussians: Gaussians, normals: Tensor | None = None, extra: dict[str, Tensor] | None = None
) -> None:
    """Write `gaussians` (and normals [N, 3], zeros when None) atomically as a binary 3DGS PLY.
    `extra` adds float properties {name: [N]} after the standard ones (e.g. an asset's materials)."""
    path = Path(path)
    g = gaussians.detach().to(device="cpu", dtype=torch.float32)
    n = len(g)
    normals = torch.zeros(n, 3) if normals is None else normals.detach().to("cpu", torch.float32)
    rest = g.sh[:, 1:].transpose(1, 2).reshape(n, 3 * (g.sh.shape[1] - 1))  # [N, 3 (K - 1)] channel-major
    extra = {name: values.detach().to("cpu", torch.float32).reshape(n, 1) for name, values in (extra or {}).items()}
    columns = torch.cat(
        [g.means, normals, g.sh[:, 0], rest, g.opacity_logits[:, None], g.log_scales, g.quats, *extra.values()], dim=1
    )
    names = property_names(g.sh.shape[1]) + list(extra)
    data = np.empty(n, dtype=[(name, "f4") for name in names])
    values = columns.numpy()
    for i, name in enumerate(names):
        data[name] = values[:, i]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = atomic_target(path)
    PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))
    os.replace(tmp, path)


def read_ply(path, extra: tuple[str, ...] = ()):
    """Gaussians [N] and normals [N, 3] (None when the file has no nx/ny/nz) from a 3DGS PLY; with
    `extra` names, also {name: [N]} of those properties (all must be present)."""
    path = Path(path)
    stage = stage_hint(path)  # a damaged artifact of a finished stage: say how to make it again

    def refuse(problem: str, hint: str = ""):
        return file_error(path, problem, stage or hint)

    if not path.exists():
        raise refuse("does not exist")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, OSError) as exc:
        raise refuse(f"is not a readable PLY file ({exc})") from None
    if "vertex" not in [e.name for e in ply.elements]:
        raise refuse("has no 'vertex' element", "expected a 3D Gaussian Splatting PLY")
    vertex = ply["vertex"].data
    names = vertex.dtype.names
    missing = [name for name in REQUIRED if name not in names]
    if missing:
        raise refuse(f"lacks the 3DGS properties {', '.join(missing)}", "expected a 3D Gaussian Splatting PLY")
    rest_names = sorted((name for name in names if re.fullmatch(r"f_rest_\d+", name)), key=lambda s: int(s[7:]))
    bases = 1 + len(rest_names) // 3
    if (
        len(rest_names) % 3
        or round(bases**0.5) ** 2 != bases
        or rest_names != [f"f_rest_{i}" for i in range(len(rest_names))]
    ):
        raise refuse(f"has {len(rest_names)} f_rest properties, which is no SH degree (expected 0, 9, 24 or 45)")

    def column(*keys) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], axis=-1))

    n = len(vertex)
    dc = column("f_dc_0", "f_dc_1", "f_dc_2")
    rest = column(*rest_names).reshape(n, 3, bases - 1).transpose(1, 2) if rest_names else torch.zeros(n, 0, 3)
    gaussians = Gaussians(
        means=column("x", "y", "z"),
        log_scales=column("scale_0", "scale_1", "scale_2"),
        quats=column("rot_0", "rot_1", "rot_2", "rot_3"),
        opacity_logits=column("opacity")[:, 0],
        sh=torch.cat([dc[:, None, :], rest], dim=1).contiguous(),
    )
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        if not torch.isfinite(getattr(gaussians, name)).all():
            raise refuse(f"has NaN or Inf values in its {name}")
    degenerate = (gaussians.quats.double().norm(dim=-1) < 1e-12).nonzero()  # no rotation: 3DGS divides by 0 here
    if len(degenerate):
        raise refuse(
            f"vertex row {int(degenerate[0])} has a zero quaternion (rot_0..3 all 0), which is no rotation "
            f"({len(degenerate)} such rows)",
            "set rot_0..3 to 1 0 0 0 (no rotation) or drop the row",
        )
    normals = column("nx", "ny", "nz") if all(k in names for k in ("nx", "ny", "nz")) else None
    if normals is not None and not torch.isfinite(normals).all():
        raise refuse("has NaN or Inf values in its normals (nx, ny, nz)")
    if not extra:
        return gaussians, normals
    absent = [name for name in extra if name not in names]
    if absent:
        raise refuse(
            f"lacks the properties {', '.join(absent)}", "is it a MatSpray asset (matspray run writes asset/asset.ply)?"
        )
    values = {name: column(name)[:, 0] for name in extra}
    if not all(torch.isfinite(v).all() for v in values.values()):
        raise refuse("has NaN or Inf values in its materials")
    return gaussians, normals, values


def vertex_count(path) -> int | None:
    """The vertex count a PLY file's header states, read without the data; None when the header does not say."""
    try:
        with open(path, "rb") as file:
            head = file.read(1 << 16)
    except OSError:
        return None
    match = re.search(rb"^element vertex (\d+)\s*$", head.split(b"end_header", 1)[0], re.MULTILINE)
    return int(match.group(1)) if match else None
