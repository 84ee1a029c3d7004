"""Nearest neighbours and farthest-point sampling on small point sets (exact, chunked, any device)."""

import torch
from torch import Tensor


def knn(queries: Tensor, points: Tensor, k: int, *, exclude_self: bool = False,
        chunk: int = 1024, exact: bool = False) -> tuple[Tensor, Tensor]:
    """The k nearest ``points`` of every query, nearest first.

    queries: Tensor  # [Q, 3] float32
    points: Tensor   # [P, 3] float32
    exclude_self: queries are ``points`` themselves; skip each one's own index.
    exact: distances from coordinate differences (no |a|^2 + |b|^2 - 2ab cancellation: for points far
           from the origin, such as the lifted points of ``control_points``)
    returns (dist2 [Q, k] float32 squared distances, idx [Q, k] int64)
    """
    extra = 1 if exclude_self else 0
    kk = min(k + extra, points.shape[0])
    mode = "donot_use_mm_for_euclid_dist" if exact else "use_mm_for_euclid_dist_if_necessary"
    # Written into tensors allocated once: small per-chunk results kept between the chunks' large
    # distance blocks fragment the heap (a million queries held ~9 GB of freed blocks resident).
    dists = torch.empty(queries.shape[0], min(k, kk), dtype=queries.dtype, device=queries.device)
    idxs = torch.empty(queries.shape[0], min(k, kk), dtype=torch.long, device=queries.device)
    for start in range(0, queries.shape[0], chunk):
        q = queries[start:start + chunk]
        d2 = torch.cdist(q, points, compute_mode=mode).square_()
        if exclude_self:
            rows = torch.arange(q.shape[0], device=q.device)
            d2[rows, rows + start] = float("inf")
        d, i = torch.topk(d2, kk, dim=1, largest=False)
        dists[start:start + q.shape[0]] = d[:, :k]
        idxs[start:start + q.shape[0]] = i[:, :k]
    return dists, idxs


def farthest_point_sampling(points: Tensor, m: int, *, start: int = 0) -> Tensor:
    """Indices of ``m`` points, each the farthest from those already chosen (greedy, deterministic).

    points: Tensor  # [N, 3] float32, N >= m
    returns Tensor  # [m] int64, distinct
    """
    n = points.shape[0]
    chosen = torch.empty(m, dtype=torch.long, device=points.device)
    nearest = torch.full((n,), float("inf"), dtype=points.dtype, device=points.device)
    current = start
    for j in range(m):
        chosen[j] = current
        nearest = torch.minimum(nearest, (points - points[current]).square().sum(-1))
        current = int(torch.argmax(nearest))
    return chosen
