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


def control_affine(control: Tensor, rotations: Tensor, translations: Tensor) -> Tensor:
    """[M, 12] row-major 3x4 maps x -> R_k (x - p_k) + p_k + T_k = R_k x + (p_k + T_k - R_k p_k)."""
    rot = quat_to_rotmat(rotations)                                                   # [M, 3, 3]
    offset = control + translations - (rot @ control[..., None])[..., 0]              # [M, 3]
    return torch.cat([rot, offset[..., None]], -1).reshape(-1, 12)


def blend(means: Tensor, quats: Tensor, affine: Tensor, rotations: Tensor, idx: Tensor,
          weights: Tensor) -> tuple[Tensor, Tensor]:
    """The skinning blend: the weighted control-point maps applied to each mean (sum_k w_k A_k, one
    3x4 map per Gaussian, then one product), the weighted rotations normalised onto each quaternion.

    means [N, 3], quats [N, 4] unit; affine [M, 12] (``control_affine``), rotations [M, 4] unit;
    idx, weights [N, K]. returns (means_t [N, 3], quats_t [N, 4] unit)
    """
    blended = torch.einsum("nk,nke->ne", weights, affine[idx]).reshape(-1, 3, 4)     # [N, 3, 4]
    means_t = (blended[..., :3] @ means[..., None])[..., 0] + blended[..., 3]
    q_blend = quat_normalize(torch.einsum("nk,nkj->nj", weights, rotations[idx]))
    return means_t, quat_multiply(q_blend, quats)


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
    return blend(means, quat_normalize(quats), control_affine(control, rotations, translations), rotations,
                 idx, weights)


def identity_rotations(m: int, *, device=None, dtype=torch.float32) -> Tensor:
    """[m, 4] identity quaternions."""
    q = torch.zeros(m, 4, device=device, dtype=dtype)
    q[:, 0] = 1.0
    return q
