"""The real spherical-harmonics basis constants of 3DGS (degree 0-3), shared by the torch reference
(matspray.render.shade.sh) and the compiled loops (matspray.render.numba.sh)."""

from __future__ import annotations

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2
