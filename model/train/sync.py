"""Data-parallel training: what the workers exchange so that they stay one run (``torch.distributed``,
any backend: gloo on CPUs; the caller sets up the process group, e.g. Ray Train: ``edmcgs.data_parallel``).

Each worker draws its samples from its own shard of the anchor windows; every step their gradients are
averaged (one all-reduce of one flat buffer), so every worker applies the same update to the same
parameters. With anchor windows only the rows of the windows the workers drew are exchanged (their
union first: a small all-gather), not every Gaussian of the recording: the bytes per step follow the
windows drawn, not the recording's length. Density control sums the workers' gradient statistics first,
and draws from generators seeded alike, so that it adds and removes the same Gaussians everywhere.
"""

from __future__ import annotations

import time

import torch
import torch.distributed as dist
from torch import Tensor

from edmcgs.model.motion.row_grad import at_rows, sparse_rows


class GradientSync:
    """The averaging of one data-parallel run (the process group must be initialised)."""

    def __init__(self) -> None:
        if not dist.is_available() or not dist.is_initialized():
            raise RuntimeError("data-parallel training needs an initialised torch.distributed process group")
        self.rank = dist.get_rank()
        self.world = dist.get_world_size()
        self.seconds = 0.0
        """Wall time in the exchanges of every step (``union``, ``average``, ``sum_``), waits for the
        slower workers included: what a run spends beyond its own computing."""
        self.bytes = 0
        """Bytes this worker contributed to those exchanges (what a network would carry, once)."""

    def _timed(self, started: float, *tensors: Tensor) -> None:
        self.seconds += time.perf_counter() - started
        self.bytes += sum(t.numel() * t.element_size() for t in tensors)

    def broadcast(self, module: torch.nn.Module) -> None:
        """Rank 0's parameters and buffers everywhere (the workers start from one model)."""
        for tensor in [*module.parameters(), *module.buffers()]:
            dist.broadcast(tensor.data, src=0)

    def union(self, rows: Tensor) -> Tensor:
        """[R] int64: every worker's ``rows`` together, ascending and unique."""
        started = time.perf_counter()
        size = torch.tensor([rows.numel()], dtype=torch.long)
        sizes = [torch.zeros_like(size) for _ in range(self.world)]
        dist.all_gather(sizes, size)
        longest = int(max(s.item() for s in sizes))
        padded = torch.full((longest,), -1, dtype=torch.long)
        padded[:rows.numel()] = rows.cpu()
        gathered = [torch.empty_like(padded) for _ in range(self.world)]
        dist.all_gather(gathered, padded)
        out = torch.unique(torch.cat(gathered))
        self._timed(started, size, padded)
        return out[out >= 0].to(rows.device)

    def average(self, optimizer: torch.optim.Optimizer, row_groups: frozenset[str],
                rows: Tensor | None) -> None:
        """Average every parameter's gradient over the workers, in one all-reduce (a worker without one
        gives zeros; a parameter no worker has a gradient for keeps none, as torch's Adam then skips
        it); for the ``row_groups`` only ``rows`` (None: all rows)."""
        started = time.perf_counter()
        parts: list[tuple[Tensor, Tensor | None]] = []
        views: list[Tensor] = []  # each gradient as it is averaged: whole, or at the rows
        had = []
        for group in optimizer.param_groups:
            for p in group["params"]:
                r = rows if group.get("name") in row_groups and rows is not None else None
                had.append(p.grad is not None)
                if p.grad is None:
                    views.append(torch.zeros_like(p) if r is None else p.new_zeros((len(r), *p.shape[1:])))
                else:
                    views.append(p.grad if r is None else at_rows(p.grad, r))
                parts.append((p, r))
        flat = torch.cat([*[view.reshape(-1) for view in views],
                          torch.tensor(had, dtype=views[0].dtype, device=views[0].device)])
        dist.all_reduce(flat)
        self._timed(started, flat)
        anyone = flat[-len(parts):] > 0
        flat = flat[:-len(parts)] / self.world
        offset = 0
        for (p, r), view, keep in zip(parts, views, anyone.tolist(), strict=True):
            chunk = flat[offset:offset + view.numel()].view_as(view)
            offset += view.numel()
            if not keep:
                p.grad = None
            elif r is None:
                p.grad = view.copy_(chunk)
            else:  # the rows alone, as a window's gradient comes (motion.row_grad)
                p.grad = sparse_rows(r, chunk, p.shape)

    def agree(self, module: torch.nn.Module) -> bool:
        """Whether every worker holds the same parameters (a checksum of each compared, bit for bit)."""
        sums = torch.stack([p.detach().double().sum() for p in module.parameters()])
        low, high = sums.clone(), sums.clone()
        dist.all_reduce(low, op=dist.ReduceOp.MIN)
        dist.all_reduce(high, op=dist.ReduceOp.MAX)
        return bool(torch.equal(low, high))

    def sum_(self, *tensors: Tensor) -> None:
        """Sum each tensor over the workers, in place."""
        started = time.perf_counter()
        for t in tensors:
            dist.all_reduce(t)
        self._timed(started, *tensors)

    def barrier(self) -> None:
        dist.barrier()
