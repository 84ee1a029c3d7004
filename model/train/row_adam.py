"""Adam that steps only some rows of the per-Gaussian parameters (a model drawn in anchor windows).

A training step of such a model draws one or two windows: the other windows' Gaussians have no
gradient. torch's Adam would still move each of them by its decaying momentum, and cost a pass over
every Gaussian of the recording per step. ``RowAdam`` steps the per-Gaussian groups on ``rows`` alone
(the trainer gives the windows drawn in the last steps, whose momentum still moves them: torch's Adam
for those; the other rows' moments wait, unchanged, until their window is drawn again) and every other
group as torch's Adam does. The state keeps torch's layout (``step``, ``exp_avg``,
``exp_avg_sq`` per parameter), so resuming and density control read and edit it as before.
"""

from __future__ import annotations

import torch
from torch import Tensor

from edmcgs.model.motion.row_grad import at_rows


class RowAdam(torch.optim.Adam):
    """torch's Adam, except that the groups named in ``row_groups`` step only ``rows`` (set before each
    step; None: every row, exactly torch's Adam). Their gradients may be sparse (``motion.row_grad``)."""

    def __init__(self, params, *, row_groups: tuple[str, ...], **kwargs):
        super().__init__(params, **kwargs)
        for group in self.param_groups:
            if group.get("name") in row_groups and (group["amsgrad"] or group["weight_decay"]
                                                    or group["maximize"]):
                raise ValueError("RowAdam's row groups support plain Adam only")
        self.row_groups = frozenset(row_groups)
        self.rows: Tensor | None = None
        """[R] int64 rows of the per-Gaussian parameters this step moves (None: all)."""

    @torch.no_grad()
    def step(self, closure=None):
        if self.rows is None:
            return super().step(closure)
        held = []  # the row groups' gradients, hidden from torch's step
        for group in self.param_groups:
            if group.get("name") in self.row_groups:
                for p in group["params"]:
                    if p.grad is not None:
                        held.append((group, p, p.grad))
                        p.grad = None
        try:
            loss = super().step(closure)
        finally:
            for _, p, grad in held:
                p.grad = grad
        for group, p, grad in held:
            self._row_step(group, p, at_rows(grad, self.rows))
        return loss

    def _row_step(self, group: dict, p: Tensor, grad: Tensor) -> None:
        """torch's Adam update (``_single_tensor_adam``) of rows ``self.rows`` of ``p``."""
        beta1, beta2 = group["betas"]
        state = self.state[p]
        if not state:
            state["step"] = torch.tensor(0.0)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        state["step"] += 1
        step = state["step"].double()  # the bias corrections as tensors: nothing read back to the host
        rows = self.rows
        exp_avg = state["exp_avg"][rows].lerp_(grad, 1 - beta1)
        exp_avg_sq = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        state["exp_avg"][rows] = exp_avg
        state["exp_avg_sq"][rows] = exp_avg_sq
        step_size = group["lr"] / (1 - beta1 ** step)
        denom = (exp_avg_sq.sqrt() / (1 - beta2 ** step).sqrt()).add_(group["eps"])
        p[rows] = p[rows] - step_size * (exp_avg / denom)
