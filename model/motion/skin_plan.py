"""Inference skinning: what a deformed state shares across times, computed once per loaded model.

At inference the canonical Gaussians and their binding are fixed, so the skinning weights, the unit
canonical rotations and the activated scales, opacities and colours are the same at every time. A
``SkinPlan`` holds them; ``skin`` then only blends the control points' transforms. It folds each
control point's rigid motion into one affine map first,

    mu_i^t = sum_k w_ik (R_k (mu_i - p_k) + p_k + T_k) = sum_k w_ik (R_k mu_i + b_k),
    b_k = p_k + T_k - R_k p_k

(the same sum as ``skinning.lbs``, regrouped: equal to float32 rounding, tested), so the per-Gaussian
work is one gather of K 3x4 maps instead of K rotations, anchors and translations.

A Gaussian whose K control points are all *frozen* (their motion over the whole span stays below the
checkpoint's threshold, see ``leanness.frozen_control_points``) keeps its canonical pose, and so does
the static set (``gaussians.STATIC``): the plan skins only the others (``moving``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from edmcgs.geometry import quat_normalize
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.motion.skinning import blend, control_affine


@dataclass
class SkinPlan:
    """The time-independent half of a deformed state.

    canonical: GaussianState  # the canonical Gaussians, activated (unit quats, linear scales ...)
    bind: Tensor              # [Nm, K] int64 control points of the moving Gaussians
    weights: Tensor           # [Nm, K] float32 their skinning weights (rows sum to 1)
    moving: Tensor | None     # [Nm] int64 indices of the Gaussians that are skinned; None: all N
    key: tuple                # identity and version of every tensor the plan was derived from
    frozen: Tensor | None     # [M] bool the frozen control points (a plan that leaves them still)
    reach: Tensor | None      # [M] float32 each point's farthest Gaussian (``leanness.control_reach``)
    points: Tensor | None     # [P] int64 the control points ``bind`` holds, sorted (drawn plans: a
                              # render moves these alone)
    """

    canonical: GaussianState
    bind: Tensor
    weights: Tensor
    moving: Tensor | None
    key: tuple
    frozen: Tensor | None = None
    reach: Tensor | None = None
    points: Tensor | None = None

    @property
    def num_moving(self) -> int:
        return int(self.bind.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the tensors the plan holds of its own (not ``frozen`` and ``reach``: shared)."""
        c = self.canonical
        own = (c.means, c.quats, c.scales, c.opacities, c.colors, self.bind, self.weights, self.moving,
               self.points)
        return sum(t.nbytes for t in own if t is not None)


def plan_key(*tensors: Tensor) -> tuple:
    """Identity and in-place version of each tensor: a plan built from them is stale when this changes
    (an optimizer step bumps ``_version``; densification swaps the Parameters)."""
    return tuple((id(t), t._version, tuple(t.shape)) for t in tensors)


@torch.no_grad()
def build_plan(canonical: GaussianState, bind: Tensor, weights: Tensor, frozen: Tensor | None,
               key: tuple, static: Tensor | None = None) -> SkinPlan:
    """A plan from the activated canonical Gaussians and their binding.

    bind, weights: Tensor  # [N, K] int64, [N, K] float32 (all Gaussians)
    frozen: Tensor | None  # [M] bool, control points that do not move; None: none frozen
    static: Tensor | None  # [N] bool, Gaussians never moved (the static set); None: none
    """
    canonical = GaussianState(canonical.means, quat_normalize(canonical.quats), canonical.scales,
                              canonical.opacities, canonical.colors).detach()
    moving = None
    still = static
    if frozen is not None and bool(frozen.any()):
        still = frozen[bind].all(-1) if still is None else still | frozen[bind].all(-1)
    if still is not None:
        moving = torch.nonzero(~still)[:, 0]
        bind, weights = bind[moving], weights[moving]
    return SkinPlan(canonical, bind.contiguous(), weights.detach().contiguous(), moving, key)


@torch.no_grad()
def skin(plan: SkinPlan, control: Tensor, rotations: Tensor, translations: Tensor) -> GaussianState:
    """The Gaussians moved by control-point transforms (the inference twin of ``skinning.lbs``).

    control: Tensor       # [M, 3] canonical control points p_k
    rotations: Tensor     # [M, 4] unit quaternions r_k^t
    translations: Tensor  # [M, 3] T_k^t
    """
    if plan.canonical.means.device.type == "cpu":
        return _skin_cpu(plan, control, rotations, translations)
    return _skin_torch(plan, control_affine(control, rotations, translations), rotations)


def _skin_torch(plan: SkinPlan, affine: Tensor, rotations: Tensor) -> GaussianState:
    """The blend in torch ops (any device)."""
    c = plan.canonical
    if plan.moving is None:
        means, quats = c.means, c.quats
    else:
        means, quats = c.means[plan.moving], c.quats[plan.moving]
    moved, turned = blend(means, quats, affine, rotations, plan.bind, plan.weights)
    if plan.moving is not None:
        moved = c.means.index_copy(0, plan.moving, moved)
        turned = c.quats.index_copy(0, plan.moving, turned)
    return GaussianState(moved, turned, c.scales, c.opacities, c.colors)


def _skin_cpu(plan: SkinPlan, control: Tensor, rotations: Tensor, translations: Tensor) -> GaussianState:
    """The same maps and blend in one numba kernel (imported here: training never loads numba)."""
    from edmcgs.model.motion.skin_fast import blend
    from edmcgs.model.render.jit import in_torch_threads

    c = plan.canonical
    means, quats = c.means.clone(), c.quats.clone()  # the frozen Gaussians keep these
    moving = plan.moving if plan.moving is not None else torch.zeros(0, dtype=torch.long)
    maps = (control.detach(), rotations.contiguous(), translations.contiguous())
    in_torch_threads(blend, c.means.numpy(), c.quats.numpy(), plan.bind.numpy(), plan.weights.numpy(),
                     *(t.numpy() for t in maps), moving.numpy(), means.numpy(), quats.numpy())
    return GaussianState(means, quats, c.scales, c.opacities, c.colors)
