"""Sparse control points that carry the motion: positions, RBF radii, skinning binding, KNN graph."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from edmcgs.model.motion.neighbors import farthest_point_sampling, knn
from edmcgs.model.motion.skinning import skinning_weights


class ControlPoints(nn.Module):
    """M canonical control points sampled from the canonical Gaussians.

    Buffers: ``positions`` [M, 3] (fixed canonical points), ``graph`` [M, K_conn] int64 (each point's
    nearest other points: the TLI and smoothness graph), ``bind`` [N, K] int64 (each Gaussian's nearest
    control points). Parameter: ``log_radius`` [M] (learnable RBF radius).
    """

    def __init__(self, positions: Tensor, log_radius: Tensor, graph: Tensor, bind: Tensor):
        super().__init__()
        self.register_buffer("positions", positions)
        self.log_radius = nn.Parameter(log_radius)
        self.register_buffer("graph", graph)
        self.register_buffer("bind", bind)

    @classmethod
    def empty(cls, m: int, n: int, skin_k: int, graph_k: int) -> ControlPoints:
        """Placeholders of the right shapes for loading a checkpoint."""
        return cls(torch.zeros(m, 3), torch.zeros(m), torch.zeros(m, graph_k, dtype=torch.long),
                   torch.zeros(n, skin_k, dtype=torch.long))

    @classmethod
    def sample(cls, means: Tensor, m: int, *, skin_k: int, graph_k: int, radius: float) -> ControlPoints:
        """Farthest-point sample ``m`` of ``means`` [N, 3] (N >= m) and bind every mean to its nearest."""
        cp = cls.empty(m, means.shape[0], skin_k, graph_k).to(means.device)
        cp.resample(means, radius=radius)
        return cp

    @property
    def num_points(self) -> int:
        return int(self.positions.shape[0])

    @torch.no_grad()
    def resample(self, means: Tensor, *, radius: float) -> None:
        """Re-sample the same number of points from ``means``, reset the radii, rebuild graph and binding."""
        idx = farthest_point_sampling(means.detach(), self.num_points)
        self.positions.copy_(means.detach()[idx])
        self.log_radius.fill_(math.log(radius))
        self.graph.copy_(knn(self.positions, self.positions, self.graph.shape[1], exclude_self=True)[1])
        self.rebind(means)

    @torch.no_grad()
    def rebind(self, means: Tensor) -> None:
        """Bind each Gaussian to its K nearest control points (after the means moved or N changed)."""
        self.bind = knn(means.detach(), self.positions, self.bind.shape[1])[1]

    def weights(self, means: Tensor) -> Tensor:
        """[N, K] normalised skinning weights of ``means`` [N, 3] (the current binding).

        The means enter detached (as in SC-GS): the weights shape the motion, not the geometry.
        """
        return skinning_weights(means.detach(), self.positions, self.log_radius, self.bind)
