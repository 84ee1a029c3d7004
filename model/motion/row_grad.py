"""Row gathers whose gradient is sparse: a step that draws one anchor window costs that window's rows.

``p[rows]``'s backward writes a zero-filled gradient the size of ``p``: for a model drawn in anchor
windows, one [N, ...] tensor per per-Gaussian parameter per step, over every Gaussian of the recording
(330 k at 60 s of full-size DAVIS346 traffic; figures: docs/benchmarks/scale.md). ``gather_rows`` gives
the same values and a sparse COO gradient holding the gathered rows alone; ``at_rows`` reads a gradient
of either layout at the rows an optimizer steps (``train/row_adam``, ``train/sync``).
"""

from __future__ import annotations

import torch
from torch import Tensor


class _GatherRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, source: Tensor, rows: Tensor) -> Tensor:
        ctx.save_for_backward(rows)
        ctx.shape = source.shape
        return source[rows]

    @staticmethod
    def backward(ctx, grad: Tensor):
        (rows,) = ctx.saved_tensors
        return sparse_rows(rows, grad, ctx.shape), None


def gather_rows(source: Tensor, rows: Tensor) -> Tensor:
    """``source[rows]``; where it takes a gradient, that gradient is sparse (rows: [R] int64)."""
    if source.requires_grad and torch.is_grad_enabled():
        return _GatherRows.apply(source, rows)
    return source[rows]


def sparse_rows(rows: Tensor, values: Tensor, shape: torch.Size) -> Tensor:
    """The sparse COO tensor of ``shape`` holding ``values`` [R, ...] at rows ``rows`` [R] (a repeated row
    sums, as gradients do)."""
    return torch.sparse_coo_tensor(rows[None], values, shape, check_invariants=False)


def at_rows(grad: Tensor, rows: Tensor) -> Tensor:
    """The dense [R, ...] values of ``grad`` at ``rows`` (sorted, unique: ``torch.unique``'s). A sparse
    ``grad`` must hold no row outside ``rows`` (the trainer steps every window a step drew)."""
    if not grad.is_sparse:
        return grad[rows]
    grad = grad.coalesce()
    out = torch.zeros((len(rows), *grad.shape[1:]), dtype=grad.dtype, device=grad.device)
    return out.index_add_(0, torch.searchsorted(rows, grad.indices()[0]), grad.values())
