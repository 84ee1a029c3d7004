"""Regularisers on the control points: temporal local isometry (TLI) and KNN Laplacian smoothness."""

from torch import Tensor


def tli_loss(points_t1: Tensor, points_t2: Tensor, graph: Tensor) -> Tensor:
    """Mean squared change of edge length between two nearby times.

    points_t1, points_t2: Tensor  # [M, 3] deformed control points at t - dt/2 and t + dt/2
    graph: Tensor                 # [M, K] int64 neighbours (edges (j, graph[j, k]))
    Zero for any rigid motion between the two times; positive for a stretch or shear.
    """
    len1 = (points_t1[:, None, :] - points_t1[graph]).norm(dim=-1)
    len2 = (points_t2[:, None, :] - points_t2[graph]).norm(dim=-1)
    return (len1 - len2).square().mean()


def laplacian_smoothness(values: Tensor, graph: Tensor) -> Tensor:
    """Mean squared difference of each point's value from the mean of its graph neighbours.

    values: Tensor  # [M, D] (g_phi's displacement per control point)
    graph: Tensor   # [M, K] int64
    """
    return (values - values[graph].mean(1)).square().sum(-1).mean()
