"""The event transition online anchors use past the span, distilled from the checkpoint's own motion.

Within its span the model moves control point j by f_theta(x_j, t) + g_phi(x_j, m_j(I_E[tau(t), t))):
the time prior carries most of the motion and g_phi corrects it. Past the span the prior stops at the
span's end and online anchors chain T(t) = T_k + g(x, I_E[A_k, t)) (``model/online/``): g alone has to
carry the motion, which g_phi was never trained to do (on the jumpingjack scene it moves the figure the
wrong way in some phases, reports/online.md).

``distill`` trains a copy of g_phi for exactly that formula on the span, where the model's own motion is
known: over sampled windows [s, t), the target is the displacement T(t) - T(s) of the full model (prior
and g_phi), the input the motion codes of I_E[s, t) seen from the state at s, as an online anchor sees
them. Half the windows start at the checkpoint's anchor before t, half anywhere up to one anchor gap
before t: an online anchor's state is not at one of the checkpoint's anchor times, and windows from
anchors alone teach the phase of the motion there. Only the copy learns (Phi, the prior and the Gaussians
stay as trained); no render, about 40 s on one CPU thread. A checkpoint carries the result as
``online_transition`` (``edmcgs distill``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import world_to_camera
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.motion.event_branch import EventTransition
from edmcgs.model.online.transition import motion_codes

SAMPLES = 3000
"""Times sampled over the span (one in five held out to measure the fit)."""
STEPS = 4000
"""Adam steps."""
BATCH = 16
"""Samples per step."""
LR = 3e-3
"""Adam step size."""


@dataclass(frozen=True)
class Distilled:
    transition: EventTransition
    samples: int
    """Times with events the fit used (training and held out)."""
    held_out_mse: dict[str, float]
    """Mean squared displacement error on the held-out times, in scene extents squared: of the distilled
    transition ("distilled"), of g_phi as trained ("g_phi") and of no motion at all ("still")."""


def distill(model: EdMCGS, event_map: Callable[[int, int], np.ndarray], *, samples: int = SAMPLES,
            steps: int = STEPS, lr: float = LR, seed: int = 0, progress: bool = False) -> Distilled:
    """The online transition of ``model`` learnt from its own motion over its span.

    event_map(a_us, b_us): the signed polarity sum of the checkpoint's recording over [a, b) at the
    event maps' size [event_height, event_width] (``TrainingData.event_map``). Raises InvalidInputError
    when the model has no event branch, or its recording gives no events over the span.
    """
    if model.transition is None:
        raise InvalidInputError("the checkpoint has no event branch: there is no transition to distill")
    if float(model.event_scale) == 0.0:
        raise InvalidInputError("the checkpoint's event branch is scaled by 0 (untrained): nothing moves "
                                "by the events")
    if samples < 5 or steps < 1:
        raise InvalidInputError(f"samples must be >= 5 and steps >= 1, got {samples} and {steps}")
    meta = model.meta
    anchors = np.asarray(meta.anchors_us, np.int64)
    if len(anchors) < 2:
        raise InvalidInputError("the checkpoint has a single anchor: its span has no motion to learn from")
    rng = np.random.default_rng(seed)
    x = model.normalize_points(model.control.positions).detach()
    unit = float(model.extent * model.event_scale)
    gap = int(np.diff(anchors).max())
    windows = model.gaussians.birth is not None
    codes, targets = [], []
    with torch.no_grad():
        for t in tqdm(rng.integers(anchors[0] + 1, anchors[-1], samples), desc="distill: samples",
                      unit="t", disable=not progress, leave=False):
            t = int(t)
            s = _anchor_before(anchors, t)
            lowest = s if windows else max(int(anchors[0]), t - gap)  # windows: states compare within one
            if rng.random() < 0.5 and lowest < t:
                s = int(rng.integers(lowest, t))
            if s >= t:
                continue
            emap = torch.as_tensor(np.asarray(event_map(s, t), np.float32))
            if not bool(torch.any(emap != 0)):
                continue
            c2w = None if meta.trajectory is None else meta.trajectory.at(t)
            start, end = _state(model, event_map, s), _state(model, event_map, t)
            code = motion_codes(model, start, emap, c2w)
            if code is not None:
                codes.append(code)
                targets.append((end - start) / unit)
    n = len(codes)
    held = np.arange(n) % 5 == 0
    train, test = np.nonzero(~held)[0], np.nonzero(held)[0]
    if len(train) == 0 or len(test) == 0:
        raise InvalidInputError(f"the recording gives events at only {n} of {samples} sampled times of the "
                                "checkpoint's span: is it the checkpoint's own recording?")
    g = copy.deepcopy(model.transition).requires_grad_(True)

    def mse(net, idx) -> torch.Tensor:
        return sum((net(x, codes[i]) - targets[i]).pow(2).sum(-1).mean() for i in idx) / len(idx)

    opt = torch.optim.Adam(g.parameters(), lr=lr)
    for _ in tqdm(range(steps), desc="distill: fit", unit="step", disable=not progress, leave=False):
        loss = mse(g, rng.choice(train, BATCH))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    g.requires_grad_(False).eval()
    with torch.no_grad():
        scores = {"distilled": float(mse(g, test)), "g_phi": float(mse(model.transition, test)),
                  "still": float(sum(targets[i].pow(2).sum(-1).mean() for i in test) / len(test))}
    return Distilled(g, n, scores)


def _anchor_before(anchors: np.ndarray, t_us: int) -> int:
    return int(anchors[np.searchsorted(anchors, t_us, side="right") - 1])


def _state(model: EdMCGS, event_map: Callable[[int, int], np.ndarray], t_us: int) -> torch.Tensor:
    """The control points' translations [M, 3] the full model gives at ``t_us`` in its span (prior and
    g_phi of the events since the anchor before it; with anchor windows, relative to that anchor)."""
    meta = model.meta
    tau = _anchor_before(np.asarray(meta.anchors_us, np.int64), t_us)
    emap = None
    if t_us > tau:
        emap = torch.as_tensor(np.asarray(event_map(tau, t_us), np.float32))
    w2c = None
    if meta.trajectory is not None:
        w2c = torch.as_tensor(world_to_camera(meta.trajectory.at(t_us)), dtype=torch.float32)
    since = meta.normalized_time(tau) if model.gaussians.birth is not None else None
    return model.control_motion(meta.normalized_time(t_us), emap, w2c, since=since)[0]


def save_with(model: EdMCGS, transition: EventTransition, path) -> None:
    """Write ``model`` with ``transition`` as its online transition to ``path`` (atomically), its frozen
    control points as the checkpoint decided them (the threshold it recorded; a version 1 checkpoint's
    none: the default)."""
    from edmcgs.model.checkpoint import save_checkpoint

    meta = model.meta
    model.online_transition = transition
    save_checkpoint(model, path, freeze_threshold=meta.freeze_threshold if meta.frozen is not None else None)
