"""3DGS adaptive density control: clone small and split large Gaussians with a large screen-space
gradient, prune transparent or huge ones, reset opacities. Keeps the optimizer's moments aligned."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from edmcgs.geometry import quat_normalize, quat_to_rotmat
from edmcgs.model.motion.gaussians import PER_GAUSSIAN, Gaussians
from edmcgs.model.train.row_adam import select_rows


class GradientStats:
    """Running mean of each Gaussian's screen-space (NDC) mean-gradient norm over the views it was seen in."""

    def __init__(self, n: int, device=None):
        self.total = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)

    def add(self, grad_ndc: Tensor, rows: Tensor | None = None) -> None:
        """grad_ndc: Tensor  # [N] norm of dL/d(mean in NDC) of one render (0 where not seen), or [R]
        of the Gaussians ``rows`` (a render of one anchor window's)."""
        seen = grad_ndc > 0
        values = torch.where(seen, grad_ndc, torch.zeros_like(grad_ndc))
        if rows is None:
            self.total += values
            self.count += seen.float()
        else:
            self.total.index_add_(0, rows, values)
            self.count.index_add_(0, rows, seen.float())

    def mean(self) -> Tensor:
        return self.total / self.count.clamp_min(1.0)

    def state_dict(self) -> dict:
        return {"total": self.total.clone(), "count": self.count.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.total, self.count = state["total"].clone(), state["count"].clone()


def screen_space_grad(means_grad: Tensor, means: Tensor, w2c: Tensor, fx: float, fy: float,
                      width: int, height: int) -> Tensor:
    """Norm of dL/d(projected mean) in NDC units, from the gradient of the world-space means.

    means_grad, means: Tensor  # [N, 3] gradient and value of the (deformed) means of one render
    w2c: Tensor                # [4, 4]
    A shift dx of a point at depth z moves its pixel by f dx / z, so dL/du = dL/dx_cam * z / f; NDC
    scales pixels by 2 / size. (The dependence of the projected footprint on the mean is neglected.)
    """
    rot = w2c[:3, :3]
    grad_cam = means_grad @ rot.T
    z = (means @ rot.T + w2c[:3, 3])[:, 2].clamp_min(1e-6)
    gu = grad_cam[:, 0] * z / fx * (width / 2)
    gv = grad_cam[:, 1] * z / fy * (height / 2)
    return torch.sqrt(gu * gu + gv * gv)


def _rebuild(optimizer: torch.optim.Optimizer, gaussians: Gaussians, keep: Tensor,
             extra: dict[str, Tensor] | None) -> None:
    """Keep the rows ``keep`` of every per-Gaussian parameter (and its Adam moments), then append
    ``extra`` rows (fresh moments)."""
    new = {}
    for name in PER_GAUSSIAN:
        old = getattr(gaussians, name)
        value = old.detach()[keep]
        if extra is not None:
            value = torch.cat([value, extra[name]])
        new[name] = value
    if gaussians.birth is not None:
        birth = gaussians.birth[keep]
        new["birth"] = birth if extra is None else torch.cat([birth, extra["birth"]])
    gaussians.replace(new)
    added = 0 if extra is None else extra["means"].shape[0]
    for group in optimizer.param_groups:
        name = group.get("name")
        if name not in PER_GAUSSIAN:
            continue
        old = group["params"][0]
        fresh = getattr(gaussians, name)
        state = optimizer.state.pop(old, None)
        if state:
            select_rows(state, keep, added)
            optimizer.state[fresh] = state
        group["params"][0] = fresh


@torch.no_grad()
def append(gaussians: Gaussians, optimizer: torch.optim.Optimizer, extra: dict[str, Tensor]) -> None:
    """Add Gaussians ``extra`` (every per-Gaussian parameter, and ``birth`` when the set has it) with
    fresh Adam moments."""
    _rebuild(optimizer, gaussians, torch.ones(len(gaussians), dtype=torch.bool,
                                              device=gaussians.means.device), extra)


@torch.no_grad()
def densify_and_prune(gaussians: Gaussians, optimizer: torch.optim.Optimizer, stats: GradientStats, *,
                      grad_threshold: float, extent: float, percent_dense: float, min_opacity: float,
                      max_size: float | None, max_count: int,
                      generator: torch.Generator | None = None) -> dict:
    """One density-control step; returns counts {cloned, split, pruned}. Resets nothing in ``stats``."""
    grads = stats.mean()
    scales = gaussians.scales()
    big = scales.max(1).values > percent_dense * extent
    selected = grads >= grad_threshold
    room = max(max_count - len(gaussians), 0)
    clone = selected & ~big
    split = selected & big
    # When near the cap, favour the largest gradients.
    if int(clone.sum()) + 2 * int(split.sum()) > room:
        order = torch.argsort(torch.where(selected, grads, torch.full_like(grads, -1.0)), descending=True)
        budget, chosen = room, torch.zeros_like(selected)
        for i in order[: int(selected.sum())].tolist():
            cost = 2 if bool(big[i]) else 1
            if cost > budget:
                continue
            chosen[i] = True
            budget -= cost
        clone, split = chosen & ~big, chosen & big

    names = PER_GAUSSIAN if gaussians.birth is None else (*PER_GAUSSIAN, "birth")
    params = {name: getattr(gaussians, name).detach() for name in names}
    cloned = {name: value[clone] for name, value in params.items()}
    # Split: two samples from each Gaussian, scales shrunk by 1.6 (as in 3DGS).
    idx = torch.nonzero(split)[:, 0].repeat(2)
    std = scales[idx]
    offsets = torch.randn(std.shape, generator=generator, device=std.device) * std
    rot = quat_to_rotmat(quat_normalize(params["quats"][idx]))
    halves = {name: value[idx] for name, value in params.items()}
    halves["means"] = halves["means"] + (rot @ offsets[..., None])[..., 0]
    halves["log_scales"] = halves["log_scales"] - math.log(1.6)
    extra = {name: torch.cat([cloned[name], halves[name]]) for name in names}

    opacity = gaussians.opacities()
    prune = opacity < min_opacity
    if max_size is not None:
        prune |= scales.max(1).values > max_size
    prune |= split
    keep = ~prune
    # Never prune everything: a scene needs at least one Gaussian to render.
    if not bool(keep.any()) and extra["means"].shape[0] == 0:
        keep = opacity >= opacity.max()
    _rebuild(optimizer, gaussians, keep, extra)
    n_split = int(split.sum())
    return {"cloned": int(clone.sum()), "split": n_split, "pruned": int((~keep).sum()) - n_split}


@torch.no_grad()
def reset_opacity(gaussians: Gaussians, optimizer: torch.optim.Optimizer, value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` and forget its Adam moments (3DGS's opacity reset)."""
    logit = math.log(value / (1 - value))
    gaussians.opacity_logits.clamp_(max=logit)
    for group in optimizer.param_groups:
        if group.get("name") == "opacity_logits":
            state = optimizer.state.get(group["params"][0])
            if state:
                state["exp_avg"].zero_()
                state["exp_avg_sq"].zero_()
