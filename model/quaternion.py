"""Differentiable quaternion algebra on torch tensors, (w, x, y, z) order, for the deformation path."""

import torch
from torch import Tensor


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b (rotation b first, then a).

    a, b: Tensor  # [..., 4] (w, x, y, z), broadcastable
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """q / |q|; a zero quaternion becomes the identity instead of NaN."""
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    return torch.where(norm > eps, q / norm.clamp_min(eps), identity)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrices of unit quaternions.

    q: Tensor  # [..., 4] (w, x, y, z), unit norm
    returns Tensor  # [..., 3, 3]
    """
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*q.shape[:-1], 3, 3)
