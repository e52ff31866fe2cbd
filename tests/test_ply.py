"""3DGS PLY files: exact round trips, the standard layout, and clear errors for bad files."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from matspray.errors import DataError
from matspray.gaussians import Gaussians
from matspray.geometry.ply import read_ply, write_ply


def random_gaussians(n, sh_bases, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, sh_bases, 3, generator=g),
    )


@pytest.mark.parametrize("sh_bases", [1, 4, 16])
def test_round_trip_is_exact(tmp_path, sh_bases):
    gaussians = random_gaussians(37, sh_bases)
    normals = torch.nn.functional.normalize(torch.randn(37, 3), dim=-1)
    write_ply(tmp_path / "g.ply", gaussians, normals)
    back, back_normals = read_ply(tmp_path / "g.ply")
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(back, name), getattr(gaussians, name)), name
    assert torch.equal(back_normals, normals)
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary file was renamed into place


def test_standard_3dgs_layout(tmp_path):
    gaussians = random_gaussians(5, 16)
    write_ply(tmp_path / "g.ply", gaussians)
    vertex = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    # 3DGS stores f_rest channel-major: f_rest_{c * 15 + k} is SH coefficient k + 1 of colour channel c
    assert np.float32(vertex["f_rest_16"][2]) == gaussians.sh[2, 2, 1]
    assert np.float32(vertex["f_rest_3"][4]) == gaussians.sh[4, 4, 0]
    assert (vertex["nx"] == 0).all()


def test_reads_files_without_normals(tmp_path):
    names = "x y z f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split()
    data = np.zeros(3, dtype=[(n, "f4") for n in names])
    data["rot_0"] = 1
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "plain.ply"))
    gaussians, normals = read_ply(tmp_path / "plain.ply")
    assert len(gaussians) == 3 and gaussians.sh.shape == (3, 1, 3) and normals is None


def test_rejects_bad_files(tmp_path):
    with pytest.raises(DataError, match="missing.ply: does not exist"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("not a ply")
    with pytest.raises(DataError, match="junk.ply: is not a readable PLY"):
        read_ply(tmp_path / "junk.ply")
    data = np.zeros(2, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(data, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(DataError, match="points.ply: lacks the 3DGS properties f_dc_0"):
        read_ply(tmp_path / "points.ply")
    gaussians = random_gaussians(2, 4)
    gaussians.means[0, 0] = float("nan")
    write_ply(tmp_path / "nan.ply", gaussians)
    with pytest.raises(DataError, match="NaN or Inf values in its means"):
        read_ply(tmp_path / "nan.ply")
