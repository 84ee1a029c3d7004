"""Gaussians at one time as a 3DGS PLY file, the layout Inria's 3DGS, SuperSplat, gsplat's viewer and SIBR
read: binary little-endian float32 ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3``,
written with ``plyfile``.

Stored as 3DGS stores its parameters: opacity as a logit, scales as logs, rotation as a unit quaternion
(w, x, y, z), colour as SH coefficients whose DC term gives colour = 0.5 + C0 * f_dc. The SH degree is
the model's: degree d has 3 ((d + 1)^2 - 1) ``f_rest`` columns, channel-major as 3DGS's ``save_ply``
flattens its [N, 3, K - 1] ``features_rest`` (every R coefficient of degrees 1..d, then G's, then B's).
A degree-0 model (plain colours) is written as its DC term; a grey model's channel is written to R, G
and B. Gaussians of exactly zero opacity (those of other anchor windows) are left out.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from edmcgs.atomic import atomic_output
from edmcgs.errors import InvalidInputError
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.render.sh import SH_C0


def ply_fields(state: GaussianState) -> dict[str, np.ndarray]:
    """The PLY columns (name -> float32 [N]) of the visible Gaussians of ``state``, in the 3DGS order."""
    with torch.no_grad():
        keep = (state.opacities.detach().cpu() > 0).nonzero().squeeze(1)
        n = len(keep)
        if n == 0:
            raise InvalidInputError("no Gaussians to export")
        means = state.means.detach().cpu()[keep].double().numpy()
        quats = torch.nn.functional.normalize(state.quats.detach().cpu()[keep].double(), dim=-1).numpy()
        scales = state.scales.detach().cpu()[keep].double().clamp_min(1e-30).numpy()
        opacity = state.opacities.detach().cpu()[keep].double().clamp(1e-7, 1 - 1e-7).numpy()
        colors = state.colors.detach().cpu()[keep].double()
    coeffs = ((colors - 0.5) / SH_C0)[:, None, :] if colors.ndim == 2 else colors  # [N, K, C]
    if coeffs.shape[2] == 1:
        coeffs = coeffs.expand(-1, -1, 3)
    coeffs = coeffs.numpy()
    out = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    out |= {name: np.zeros(n) for name in ("nx", "ny", "nz")}
    out |= {f"f_dc_{c}": coeffs[:, 0, c] for c in range(3)}
    rest = coeffs[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # 3DGS: channel-major
    out |= {f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])}
    out["opacity"] = np.log(opacity / (1 - opacity))
    out |= {f"scale_{i}": np.log(scales[:, i]) for i in range(3)}
    out |= {f"rot_{i}": quats[:, i] for i in range(4)}
    fields = {k: v.astype(np.float32) for k, v in out.items()}
    bad = [k for k, v in fields.items() if not np.isfinite(v).all()]
    if bad:
        raise InvalidInputError(f"the Gaussians have non-finite {', '.join(bad)}: nothing written")
    return fields


def ply_data(state: GaussianState) -> PlyData:
    """The PLY of ``state``: one ``vertex`` element of float32 columns, binary little-endian."""
    fields = ply_fields(state)
    n = len(next(iter(fields.values())))
    table = np.empty(n, dtype=[(k, "<f4") for k in fields])
    for k, v in fields.items():
        table[k] = v
    return PlyData([PlyElement.describe(table, "vertex")], text=False, byte_order="<")


def ply_bytes(state: GaussianState) -> bytes:
    """The PLY file of ``state`` (header and binary table) in memory."""
    buf = io.BytesIO()
    ply_data(state).write(buf)
    return buf.getvalue()


def write_ply(state: GaussianState, path: str | os.PathLike) -> Path:
    """Write ``state`` to ``path`` (atomically); returns the path."""
    data = ply_data(state)
    path = Path(path)
    with atomic_output(path, InvalidInputError) as tmp, open(tmp, "wb") as fh:
        data.write(fh)
    return path
