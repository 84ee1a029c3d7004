"""View-dependent colour from real spherical harmonics of degree 0..3 (the 3DGS basis and constants)."""

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

NUM_COEFFS = {1: 0, 4: 1, 9: 2, 16: 3}
"""Coefficients per channel K = (degree + 1)^2 -> degree."""


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """The real SH basis at unit directions.

    dirs: Tensor  # [N, 3] unit vectors
    returns Tensor  # [N, (degree + 1)^2]
    """
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
        if degree > 2:
            out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                    SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                    SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def sh_to_color(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Colour seen along ``dirs``: the SH expansion + 0.5, clamped at 0 (as in 3DGS).

    coeffs: Tensor  # [N, K, C], K in {1, 4, 9, 16}
    dirs: Tensor    # [N, 3] unit vectors from the camera centre to each Gaussian
    returns Tensor  # [N, C]
    """
    basis = sh_basis(dirs, NUM_COEFFS[coeffs.shape[1]])
    return (torch.einsum("nk,nkc->nc", basis, coeffs) + 0.5).clamp_min(0.0)
