"""Sparse control points that carry the motion: positions, RBF radii, skinning binding, KNN graph."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from edmcgs.model.motion.neighbors import farthest_point_sampling, knn
from edmcgs.model.motion.skinning import skinning_weights

WINDOW_SEPARATION = 1e3
"""With anchor windows, sampling, binding and the graph measure distances in (x, y, z, this * window):
a Gaussian binds to control points of its own window first, and farthest-point sampling covers every
window (a window's movers get their own control points, whatever other windows have at that place)."""


class ControlPoints(nn.Module):
    """M canonical control points sampled from the canonical Gaussians.

    Buffers: ``positions`` [M, 3] (fixed canonical points), ``graph`` [M, K_conn] int64 (each point's
    nearest other points: the TLI and smoothness graph), ``bind`` [N, K] int64 (each Gaussian's nearest
    control points), ``birth`` [M] int64 or None (the anchor window of each point, with anchor windows).
    Parameter: ``log_radius`` [M] (learnable RBF radius).
    """

    def __init__(self, positions: Tensor, log_radius: Tensor, graph: Tensor, bind: Tensor,
                 birth: Tensor | None = None):
        super().__init__()
        self.register_buffer("positions", positions)
        self.log_radius = nn.Parameter(log_radius)
        self.register_buffer("graph", graph)
        self.register_buffer("bind", bind)
        self.register_buffer("birth", birth)

    @classmethod
    def empty(cls, m: int, n: int, skin_k: int, graph_k: int, *, birth: bool = False) -> ControlPoints:
        """Placeholders of the right shapes for loading a checkpoint."""
        return cls(torch.zeros(m, 3), torch.zeros(m), torch.zeros(m, graph_k, dtype=torch.long),
                   torch.zeros(n, skin_k, dtype=torch.long),
                   torch.zeros(m, dtype=torch.long) if birth else None)

    @classmethod
    def sample(cls, means: Tensor, m: int, *, skin_k: int, graph_k: int, radius: float,
               birth: Tensor | None = None) -> ControlPoints:
        """Farthest-point sample ``m`` of ``means`` [N, 3] (N >= m) and bind every mean to its nearest;
        ``birth`` [N]: the Gaussians' anchor windows (see ``WINDOW_SEPARATION``)."""
        cp = cls.empty(m, means.shape[0], skin_k, graph_k, birth=birth is not None).to(means.device)
        cp.resample(means, radius=radius, birth=birth)
        return cp

    @property
    def num_points(self) -> int:
        return int(self.positions.shape[0])

    @torch.no_grad()
    def resample(self, means: Tensor, *, radius: float, birth: Tensor | None = None) -> None:
        """Re-sample the same number of points from ``means``, reset the radii, rebuild graph and binding
        (``birth``: the Gaussians' anchor windows, needed when the points have windows). The static set
        (birth ``STATIC``: never moved) gets none while there are enough other Gaussians (it is then
        only bound, which its skinning ignores)."""
        pool = torch.arange(means.shape[0], device=means.device)
        if birth is not None and int((birth >= 0).sum()) >= self.num_points:
            pool = torch.nonzero(birth >= 0)[:, 0]
        lifted = _lift(means.detach()[pool], None if birth is None else birth[pool])
        idx = pool[farthest_point_sampling(lifted, self.num_points)]
        self.positions.copy_(means.detach()[idx])
        if self.birth is not None:
            self.birth.copy_(birth[idx])
        self.log_radius.fill_(math.log(radius))
        points = _lift(self.positions, self.birth)
        exact = self.birth is not None
        self.graph.copy_(knn(points, points, self.graph.shape[1], exclude_self=True, exact=exact)[1])
        self.rebind(means, birth=birth)

    @torch.no_grad()
    def rebind(self, means: Tensor, *, birth: Tensor | None = None) -> None:
        """Bind each Gaussian to its K nearest control points (after the means moved or N changed)."""
        if self.birth is not None and birth is None:
            raise ValueError("these control points have anchor windows: rebind needs the Gaussians' birth")
        queries = _lift(means.detach(), birth if self.birth is not None else None)
        self.bind = knn(queries, _lift(self.positions, self.birth), self.bind.shape[1],
                        exact=self.birth is not None)[1]

    def weights(self, means: Tensor) -> Tensor:
        """[N, K] normalised skinning weights of ``means`` [N, 3] (the current binding).

        The means enter detached (as in SC-GS): the weights shape the motion, not the geometry.
        """
        return skinning_weights(means.detach(), self.positions, self.log_radius, self.bind)


def _lift(points: Tensor, birth: Tensor | None) -> Tensor:
    """[N, 3] points, or [N, 4] with the anchor window as a far-apart fourth coordinate."""
    if birth is None:
        return points
    return torch.cat([points, birth.to(points.dtype)[:, None] * WINDOW_SEPARATION], -1)
