"""Linear blend skinning of Gaussians by control points (SC-GS's formulation).

A Gaussian i bound to control points k in N(i) with weights w_ik (sum 1) moves as

    mu_i^t = sum_k w_ik (R_k^t (mu_i - p_k) + p_k + T_k^t),   q_i^t = normalize(sum_k w_ik r_k^t) * q_i

where p_k is the canonical control point, r_k^t / R_k^t its rotation and T_k^t its translation at t.
"""

import torch
from torch import Tensor

from edmcgs.geometry import quat_multiply, quat_normalize, quat_to_rotmat


def skinning_weights(means: Tensor, control: Tensor, log_radius: Tensor, idx: Tensor) -> Tensor:
    """Normalised Gaussian-RBF weights of each Gaussian's bound control points.

    means: Tensor       # [N, 3] canonical Gaussian means
    control: Tensor     # [M, 3] canonical control points
    log_radius: Tensor  # [M] log of each control point's RBF radius (learnable)
    idx: Tensor         # [N, K] int64 bound control points
    returns Tensor      # [N, K], rows sum to 1 (a softmax of -d^2 / 2r^2: no 0/0 when all are far)
    """
    d2 = (means[:, None, :] - control[idx]).square().sum(-1)
    return torch.softmax(-0.5 * d2 * torch.exp(-2.0 * log_radius[idx]), dim=-1)


def lbs(means: Tensor, quats: Tensor, control: Tensor, rotations: Tensor, translations: Tensor,
        idx: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Move Gaussians by their control points' rigid transforms.

    means: Tensor         # [N, 3] canonical means
    quats: Tensor         # [N, 4] canonical rotations (w, x, y, z)
    control: Tensor       # [M, 3] canonical control points p_k
    rotations: Tensor     # [M, 4] unit quaternions r_k^t
    translations: Tensor  # [M, 3] T_k^t
    idx, weights: Tensor  # [N, K] int64, [N, K] float32 (rows sum to 1)
    returns (means_t [N, 3], quats_t [N, 4] unit)
    """
    rot = quat_to_rotmat(rotations)[idx]                        # [N, K, 3, 3]
    anchor = control[idx]                                       # [N, K, 3]
    local = (means[:, None, :] - anchor)[..., None]             # [N, K, 3, 1]
    moved = (rot @ local)[..., 0] + anchor + translations[idx]  # [N, K, 3]
    means_t = (weights[..., None] * moved).sum(1)
    blended = quat_normalize((weights[..., None] * rotations[idx]).sum(1))
    quats_t = quat_multiply(blended, quat_normalize(quats))
    return means_t, quats_t


def identity_rotations(m: int, *, device=None, dtype=torch.float32) -> Tensor:
    """[m, 4] identity quaternions."""
    q = torch.zeros(m, 4, device=device, dtype=dtype)
    q[:, 0] = 1.0
    return q
