"""Adam that steps only some rows of the per-Gaussian parameters (a model drawn in anchor windows).

A training step of such a model draws one or two windows: the other windows' Gaussians have no
gradient. torch's Adam would still move each of them by its decaying momentum, and cost a pass over
every Gaussian of the recording per step. ``RowAdam`` is lazy: a step moves the rows it is given
alone, and a row left out waits, its momentum moves owed. With no gradient Adam's moments only decay
(``m beta1^i``, ``v beta2^i``), so the owed moves are a closed form, ``owed[last] m / sqrt(v)``, paid at
once when the row is needed again: ``catch_up`` (the trainer calls it for the windows a step draws,
before they are read) and ``flush`` (every row, before the model is read whole: evaluation, density
control, checkpoints). The path is torch's Adam's, to float rounding and a ``1e-12`` momentum tail.

State per row-group parameter: torch's ``exp_avg`` and ``exp_avg_sq`` (density control edits them with
``select_rows``), ``step`` (a Python int: reading it costs a GPU nothing), ``row_step`` (the step each
row is current to) and ``owed`` (``owed[L]``: what a row current to step L owes by now, per unit of
``m / sqrt(v)``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from edmcgs.model.motion.row_grad import at_rows

TAIL = 1e-12
"""The owed moves are summed until they fall below this fraction of the first (264 steps at the default
betas)."""

_LAZY_KEYS = ("row_step", "owed")


class RowAdam(torch.optim.Adam):
    """torch's Adam, except that the groups named in ``row_groups`` step only ``rows`` (set before each
    step, after ``catch_up(rows)``; None: every row). Their gradients may be sparse (``motion.row_grad``)."""

    def __init__(self, params, *, row_groups: tuple[str, ...], **kwargs):
        super().__init__(params, **kwargs)
        for group in self.param_groups:
            if group.get("name") not in row_groups:
                continue
            if group["amsgrad"] or group["weight_decay"] or group["maximize"]:
                raise ValueError("RowAdam's row groups support plain Adam only")
            beta1, beta2 = group["betas"]
            if not beta1 < math.sqrt(beta2):  # else the owed moves grow instead of decaying
                raise ValueError(f"RowAdam needs beta1 < sqrt(beta2), not betas {group['betas']}")
        self.row_groups = frozenset(row_groups)
        self._power_cache: dict[tuple, Tensor] = {}
        self.rows: Tensor | None = None
        """[R] sorted unique int64 rows of the per-Gaussian parameters this step moves (None: all)."""

    def _row_params(self):
        for group in self.param_groups:
            if group.get("name") in self.row_groups:
                for p in group["params"]:
                    yield group, p

    @torch.no_grad()
    def step(self, closure=None):
        held = []  # the row groups' gradients, hidden from torch's step
        for group, p in self._row_params():
            if p.grad is not None:
                held.append((group, p, p.grad))
                p.grad = None
        try:
            loss = super().step(closure)
        finally:
            for _, p, grad in held:
                p.grad = grad
        for group, p, grad in held:
            self._row_step(group, p, grad)
        return loss

    @torch.no_grad()
    def catch_up(self, rows: Tensor | None = None) -> None:
        """Pay ``rows``' owed momentum moves (None: every row's): they read as torch's Adam would have
        left them after the last step."""
        index = slice(None) if rows is None else rows
        for group, p in self._row_params():
            if self.state[p]:
                state = self._state(p)
                x, m, v = p[index], state["exp_avg"][index], state["exp_avg_sq"][index]
                self._pay(group, state, index, x, m, v)
                p[index], state["exp_avg"][index], state["exp_avg_sq"][index] = x, m, v
                state["row_step"][index] = state["step"]

    def reach(self, p: Tensor) -> float:
        """The farthest any coordinate of a row of ``p`` (a row-group parameter) can move when caught up:
        the largest owed move times the largest |m| / sqrt(v) Adam can hold, (1 - beta1) / sqrt((1 - beta2)
        (1 - beta1^2 / beta2)) (Cauchy-Schwarz over the past gradients). 0 before its first step."""
        state = self.state[p]
        if not state or "owed" not in state:
            return 0.0
        group = next(g for g, q in self._row_params() if q is p)
        beta1, beta2 = group["betas"]
        ratio = (1 - beta1) / math.sqrt((1 - beta2) * (1 - beta1 ** 2 / beta2))
        return float(state["owed"][:state["step"] + 1].max()) * ratio

    def flush(self) -> None:
        """Every row current (``catch_up`` of all)."""
        self.catch_up(None)

    def _state(self, p: Tensor) -> dict:
        state = self.state[p]
        if not state:
            state["step"] = 0
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        if "row_step" not in state:  # new, or a state torch's Adam left: every row current
            state["step"] = step = int(state["step"])
            state["row_step"] = torch.full((len(p),), step, dtype=torch.long, device=p.device)
            state["owed"] = torch.zeros(max(2 * step, 64), dtype=torch.float64, device=p.device)
        return state

    @staticmethod
    def _pay(group: dict, state: dict, index, x: Tensor, m: Tensor, v: Tensor) -> None:
        """Apply in place to the gathered rows ``x`` (parameter), ``m``, ``v`` (moments) the momentum
        moves of the steps after their ``row_step`` (none for a current row)."""
        beta1, beta2 = group["betas"]
        last = state["row_step"][index]
        shape = (-1,) + (1,) * (x.dim() - 1)
        # eps is left out of the decaying denominator: at 1e-15 beside sqrt(v) it is below float rounding
        x.sub_(state["owed"][last].to(x.dtype).view(shape) * m / (v.sqrt() + group["eps"]))
        idle = (state["step"] - last).double().view(shape)
        m.mul_((beta1 ** idle).to(m.dtype))
        v.mul_((beta2 ** idle).to(v.dtype))

    def _row_step(self, group: dict, p: Tensor, grad: Tensor) -> None:
        """torch's Adam update (``_single_tensor_adam``) of rows ``self.rows`` of ``p`` (current: the
        caller's ``catch_up`` of them paid what they owed); then the move every waiting row owes for this
        step added to ``owed``."""
        beta1, beta2 = group["betas"]
        state = self._state(p)
        rows = self.rows
        index = slice(None) if rows is None else rows
        if rows is None:
            grad = grad.to_dense() if grad.is_sparse else grad
        else:
            grad = at_rows(grad, rows)
        x, m, v = p[index], state["exp_avg"][index], state["exp_avg_sq"][index]
        state["step"] = step = state["step"] + 1
        step_size = group["lr"] / (1 - beta1 ** step)
        bias2 = math.sqrt(1 - beta2 ** step)
        m.lerp_(grad, 1 - beta1)
        v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        x.sub_(step_size * (m / (v.sqrt() / bias2).add_(group["eps"])))
        p[index], state["exp_avg"][index], state["exp_avg_sq"][index] = x, m, v
        state["row_step"][index] = step
        # A row current to step L < step moves at this step by step_size bias2 ratio^(step - L) m / sqrt(v)
        # (its m and v as at L): summed into owed[L] for the last `horizon` values of L.
        owed = state["owed"]
        if len(owed) <= step:
            state["owed"] = owed = torch.cat([owed, torch.zeros_like(owed)])
        powers = self._powers(group, owed.device)
        first = max(step - len(powers), 0)
        owed[first:step] += step_size * bias2 * powers[len(powers) - (step - first):]

    def _powers(self, group: dict, device: torch.device) -> Tensor:
        """[horizon] float64 ratio^horizon ... ratio^1, ratio = beta1 / sqrt(beta2), to the ``TAIL``."""
        beta1, beta2 = group["betas"]
        key = (beta1, beta2, device)
        if key not in self._power_cache:
            ratio = beta1 / math.sqrt(beta2)
            horizon = math.ceil(math.log(TAIL) / math.log(ratio))
            self._power_cache[key] = ratio ** torch.arange(horizon, 0, -1, dtype=torch.float64, device=device)
        return self._power_cache[key]

    def load_state_dict(self, state_dict: dict) -> None:
        # torch would cast every state tensor to its parameter's dtype: row_step and owed keep theirs
        state_dict = {**state_dict, "state": {k: dict(s) for k, s in state_dict["state"].items()}}
        lazy = {k: {key: s.pop(key) for key in _LAZY_KEYS if key in s}
                for k, s in state_dict["state"].items()}
        super().load_state_dict(state_dict)
        params = [p for group in self.param_groups for p in group["params"]]
        for k, values in lazy.items():
            self.state[params[k]].update({key: value.to(params[k].device) for key, value in values.items()})
        for _, p in self._row_params():  # torch's Adam made the step a tensor again
            if "step" in self.state[p]:
                self.state[p]["step"] = int(self.state[p]["step"])


def select_rows(state: dict, keep: Tensor, added: int) -> None:
    """Edit a per-Gaussian parameter's Adam ``state`` in place to its rows ``keep`` followed by ``added``
    fresh ones (zero moments, current to the last step); a state torch's Adam made works too."""
    for key in ("exp_avg", "exp_avg_sq", "row_step"):
        if key not in state:
            continue
        value = state[key][keep]
        if added:
            fill = state["step"] if key == "row_step" else 0
            value = torch.cat([value, value.new_full((added, *value.shape[1:]), fill)])
        state[key] = value
