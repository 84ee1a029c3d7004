"""The sinusoidal positional encoding gamma(.) of NeRF / Deformable 3DGS."""

import math

import torch
from torch import Tensor


def positional_encoding(x: Tensor, num_freqs: int) -> Tensor:
    """gamma(x) = [x, sin(2^k pi x), cos(2^k pi x)]_{k<L}.

    x: Tensor  # [..., D] float32, expected in about [-1, 1]
    returns Tensor  # [..., D * (1 + 2 L)]
    """
    if num_freqs == 0:
        return x
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi
    angles = (x[..., None, :] * freqs[:, None]).flatten(-2)  # [..., L * D]
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


def encoded_size(dim: int, num_freqs: int) -> int:
    """Width of ``positional_encoding`` of a ``dim``-vector."""
    return dim * (1 + 2 * num_freqs)
