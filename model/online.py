"""Online anchors: the control-point state at a new APS frame past the checkpoint's span, predicted by
the model's own event-driven transition and corrected against the frame.

An anchor's state is the control-point motion (translations [M, 3], rotations [M, 4]) at its time; the
Gaussians follow by skinning. Past the span the time prior f_theta has no data: its time input is
clamped to the span's end (``SceneMeta.normalized_time`` clamps), so it contributes a constant and the
events carry the motion:

    checkpoint anchor L (the last):  T_L = f_theta(x, t_L)                     (as trained)
    first online anchor A_1:         T_1 = f_theta(x, 1) + g(x, I_E[L, A_1))   (g = g_phi: deform(A_1))
    online anchor A_k, k > 1:        T_k = T_{k-1} + g(x, I_E[A_{k-1}, A_k)),  R_k = R_{k-1}
    a render at t in [A_k, A_k+1):   T(t) = T_k + g(x, I_E[A_k, t))

with g the transition the server chose past the span (see below).

A checkpoint drawn in anchor windows (the ``real`` preset) draws, at each time, only the Gaussians of
the window it falls in, moved relative to that window's anchor; past the span that is the last window, so
online anchors carry its Gaussians forward (the prior taken relative to the last anchor, as ``deform``
does there). A background layer is drawn behind them, in the fit as in the served render.

``correct`` refines a predicted state against the frame: a per-control-point translation residual,
optimised for a bounded number of Adam steps on the photometric loss through the differentiable
rasterizer, with the canonical Gaussians and the networks frozen; with ``colour_lr`` > 0, per-Gaussian
colour offsets learnt in the same steps (online appearance: what the stream shows that the checkpoint
never saw, its views past the training ones). The offsets carry from each anchor to the next and each
correction refines them, so they accumulate what the frames showed. Which transition moves the anchors
past the span (g_phi, the checkpoint's distilled one of ``model/online_distill.py``, or none) the server
chooses by how well each predicted the recent frames (``prediction_losses``); ``finetune`` (off by
default) lets a copy of it learn from the corrections.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import Tensor

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics, project, world_to_camera
from edmcgs.model.dynamic import NEAR, EdMCGS, background_color, render_image
from edmcgs.model.motion.event_branch import sample_global, sample_local
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.motion.skin_plan import skin
from edmcgs.model.render.sh import SH_C0

Motion = tuple[Tensor, Tensor]
"""(translations [M, 3], rotations [M, 4]) of the control points."""


@torch.no_grad()
def checkpoint_motion(model: EdMCGS, t_us: int) -> Motion:
    """The model's own motion at ``t_us`` from its checkpoint anchor, without events (prior clamped past
    the span); the first online anchor's state before its events move it."""
    window = last_window(model)
    since = None if window is None else model.meta.normalized_time(int(model.meta.anchors_us[window]))
    trans, rot, _ = model.control_motion(model.meta.normalized_time(int(t_us)), None, since=since)
    return trans, rot


def last_window(model: EdMCGS) -> int | None:
    """The anchor window whose Gaussians online anchors carry forward (the last one), or None when the
    model has no anchor windows (every Gaussian is drawn at every time)."""
    return None if model.gaussians.birth is None else len(model.meta.anchors_us) - 1


@torch.no_grad()
def event_displacement(model: EdMCGS, base_trans: Tensor, event_map: np.ndarray | Tensor | None,
                       ev_c2w: np.ndarray | None, transition: torch.nn.Module | None = None) -> Tensor:
    """g_phi's displacement [M, 3] of the control points from the state ``base_trans`` by the events
    ``event_map`` ([He, We] signed polarity sum); zeros without an event branch or events.
    transition: g_phi to use (default: the model's; ``finetune`` makes online copies)."""
    codes = motion_codes(model, base_trans, event_map, ev_c2w)
    if codes is None:
        return torch.zeros_like(model.control.positions)
    g = model.transition if transition is None else transition
    return g(model.normalize_points(model.control.positions), codes) * (model.extent * model.event_scale)


@torch.no_grad()
def motion_codes(model: EdMCGS, base_trans: Tensor, event_map: np.ndarray | Tensor | None,
                 ev_c2w: np.ndarray | None) -> Tensor | None:
    """The control points' motion codes [M, 32] of ``event_map`` seen from the state ``base_trans``
    (Phi, then local or global sampling); None without an event branch or events."""
    cp = model.control.positions
    if model.transition is None or event_map is None:
        return None
    emap = torch.as_tensor(event_map, dtype=torch.float32, device=cp.device)
    if not bool(torch.any(emap != 0)):
        return None
    feats = model.encoder(model.config.contrast_threshold * emap[None, None])[0]
    if model.config.local_sampling:
        if ev_c2w is None:
            raise InvalidInputError("ev_c2w is needed to project control points on the event camera")
        w2c = torch.as_tensor(world_to_camera(np.asarray(ev_c2w, np.float64)), dtype=torch.float32,
                              device=cp.device)
        intr = model.meta.event_intrinsics
        uv, depth = project(cp + base_trans, w2c, intr)
        return sample_local(feats, uv, depth > NEAR, intr.width, intr.height)
    return sample_global(feats, cp.shape[0])


def advance(model: EdMCGS, motion: Motion, event_map, ev_c2w,
            transition: torch.nn.Module | None = None) -> Motion:
    """The Markov transition from an anchor's ``motion`` by the events since it (``transition``: as in
    ``event_displacement``)."""
    trans, rot = motion
    return trans + event_displacement(model, trans, event_map, ev_c2w, transition), rot


@torch.no_grad()
def prediction_losses(model: EdMCGS, motions: list[Motion], spawned: GaussianState | None, image: np.ndarray,
                      c2w: np.ndarray, intrinsics: Intrinsics, *, scale: float = 1.0,
                      colors: Tensor | None = None) -> list[float]:
    """L1 of each control-point motion's render (forward only, at ``scale`` of the frame's size, with the
    colour offsets ``colors``) against ``image`` (uint8 [H, W, C]) seen from ``c2w``: how well each
    prediction explains a new frame."""
    target, intr = fit_target(image, intrinsics, scale)
    target = target.numpy()
    return [float(np.abs(model.render(with_spawned(state_of(model, m, colors), spawned), c2w, intr, threads=1)
                         - target).mean()) for m in motions]


def fit_target(image: np.ndarray, intrinsics: Intrinsics, scale: float) -> tuple[Tensor, Intrinsics]:
    """(float32 [h, w, C] in [0, 1], the camera at that size): a uint8 frame area-downsampled to
    ``scale`` of its size (at least 8 pixels a side)."""
    target = torch.as_tensor(image, dtype=torch.float32) / 255.0
    if scale == 1.0:
        return target, intrinsics
    w, h = max(8, round(intrinsics.width * scale)), max(8, round(intrinsics.height * scale))
    target = torch.nn.functional.interpolate(target.permute(2, 0, 1)[None], size=(h, w),
                                             mode="area")[0].permute(1, 2, 0)
    return target, intrinsics.scaled(w, h)


def finetune(model: EdMCGS, transition: torch.nn.Module, prev_motion: Motion, event_map, ev_c2w,
             target_trans: Tensor, *, steps: int, lr: float) -> tuple[torch.nn.Module, float, float] | None:
    """A copy of ``transition`` (g_phi) after ``steps`` Adam steps toward predicting ``target_trans`` (a
    corrected anchor) from ``prev_motion`` (the anchor before it) by the events between them: later
    predictions learn from the corrections. Phi, the prior and the Gaussians stay frozen; ``transition``
    itself is untouched (renders may be reading it). Returns (copy, loss before, loss after: mean squared
    displacement error in g_phi's units), or None when the events give g_phi nothing to learn from."""
    codes = motion_codes(model, prev_motion[0], event_map, ev_c2w)
    if codes is None or steps <= 0:
        return None
    tuned = copy.deepcopy(transition).requires_grad_(True)
    x = model.normalize_points(model.control.positions)
    target = ((target_trans - prev_motion[0]) / (model.extent * model.event_scale)).detach()
    opt = torch.optim.Adam(tuned.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        loss = (tuned(x, codes) - target).pow(2).sum(-1).mean()
        losses.append(float(loss.detach()))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    tuned.requires_grad_(False)
    with torch.no_grad():
        after = float((tuned(x, codes) - target).pow(2).sum(-1).mean())
    return tuned, losses[0], after


@torch.no_grad()
def state_of(model: EdMCGS, motion: Motion, colors: Tensor | None = None) -> GaussianState:
    """The Gaussians of a control-point motion (every Gaussian skinned: past the span nothing is frozen),
    with the colour offsets ``colors`` [N, C] learnt online (``correct``) when given."""
    trans, rot = motion
    state = skin(model.skin_plan(frozen=False), model.control.positions, rot, trans)
    visible = model.gaussians.visible_in(last_window(model))
    opacities = state.opacities if visible is None else state.opacities * visible.to(state.opacities.device)
    return GaussianState(state.means, state.quats, state.scales, opacities,
                         state.colors if colors is None else recolored(state.colors, colors))


def recolored(colors: Tensor, offsets: Tensor) -> Tensor:
    """Colours (RGB [N, C], or SH [N, K, C]: their base colour, the DC term) moved by ``offsets`` [N, C]."""
    if colors.dim() == 3:
        return torch.cat([colors[:, :1] + (offsets / SH_C0)[:, None], colors[:, 1:]], 1)
    return colors + offsets


def correct(model: EdMCGS, motion: Motion, image: np.ndarray, c2w: np.ndarray, intrinsics: Intrinsics, *,
            steps: int, lr: float = 6e-3, scale: float = 1.0, reg: float = 1e-2,
            colors: Tensor | None = None,
            colour_lr: float = 0.0) -> tuple[Motion, Tensor | None, float, float]:
    """Fit a translation residual (and, with ``colour_lr`` > 0, colour offsets) to ``image`` (uint8
    [H, W, C]) seen from ``c2w``.

    steps: Adam steps (0: no fit); lr: step size as a fraction of the scene's extent; scale: render and
    compare at this fraction of the frame's size (the target is area-downsampled); reg: weight of the
    residual's squared norm (in extents); colors: the colour offsets [N, C] the state carries (None:
    none yet); colour_lr: their step size (0: they stay as given). Returns (corrected motion, colour
    offsets, L1 loss at the first step, L1 loss at the last step, before its update: no extra render to
    score the result).
    """
    trans0, rot = motion
    target, intr = fit_target(image, intrinsics, scale)
    w2c = torch.as_tensor(world_to_camera(np.asarray(c2w, np.float64)), dtype=torch.float32)
    layer = model.bg_layer
    bg = background_color(model.config, model.meta.channels)
    extent = float(model.extent)
    delta = torch.zeros_like(trans0, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=lr)
    offsets, learn = colors, colour_lr > 0 and steps > 0
    if learn:
        n, c = model.gaussians.means.shape[0], model.meta.channels
        offsets = (torch.zeros(n, c, device=trans0.device) if colors is None else colors.detach().clone())
        offsets.requires_grad_(True)
        opt.add_param_group({"params": [offsets], "lr": colour_lr})
    # Skinning is linear in the translations: sum_k w_ik (R_k (mu_i - p_k) + p_k + T_k + d_k) moves mean
    # i by sum_k w_ik d_k, and no rotation changes. Skin once, then each step adds the blended residual.
    with torch.no_grad():
        base = model.state_from_motion(trans0, rot, last_window(model))
        behind = None if layer is None else layer.image(np.asarray(c2w, np.float64)[:3, :3], intr)
        cp = model.control
        weights = cp.weights(model.gaussians.means)[..., None]                        # [N, K, 1]
    first = last = None
    for _ in range(steps):
        moved = base.means + (weights * delta[cp.bind]).sum(1) * extent
        state = GaussianState(moved, base.quats, base.scales, base.opacities,
                              base.colors if offsets is None else recolored(base.colors, offsets))
        out = render_image(state, w2c, intr, bg, behind)
        loss = (out - target).abs().mean()
        value = float(loss.detach())
        first = value if first is None else first
        last = value
        opt.zero_grad(set_to_none=True)
        (loss + reg * delta.pow(2).sum(-1).mean()).backward()
        opt.step()
    if learn:
        offsets = offsets.detach()
    if first is None:
        return (trans0, rot), offsets, float("nan"), float("nan")
    return (trans0 + delta.detach() * extent, rot), offsets, first, last


@torch.no_grad()
def spawn(model: EdMCGS, state: GaussianState, image: np.ndarray, c2w: np.ndarray, intrinsics: Intrinsics,
          *, limit: int, threshold: float = 0.08, opacity: float = 0.9) -> GaussianState | None:
    """Gaussians for what the frame shows that the render of ``state`` lacks (an anchor window carried
    forward has no Gaussians for what entered the view since): at most ``limit`` of them, on a regular
    grid over the pixels where ``image`` (uint8 [H, W, C]) differs from the render by more than
    ``threshold`` (of 1), each backprojected at the median depth of the drawn Gaussians (the scene's
    depth where nothing better is known), coloured by the frame, sized to cover its grid cell. Static:
    the events do not move them. None when nothing differs or ``limit`` is 0."""
    if limit <= 0:
        return None
    frame = np.asarray(image, np.float32) / 255.0
    rendered = model.render(state, c2w, intrinsics)
    differs = np.abs(rendered - frame).max(-1) > threshold
    count = int(differs.sum())
    if count == 0:
        return None
    stride = max(1, int(np.ceil(np.sqrt(count / limit))))
    grid = np.zeros_like(differs)
    grid[stride // 2::stride, stride // 2::stride] = True
    ys, xs = np.nonzero(differs & grid)
    if len(ys) == 0:
        return None
    keep = np.linspace(0, len(ys) - 1, min(len(ys), limit)).round().astype(np.int64)
    ys, xs = ys[keep], xs[keep]
    c2w = np.asarray(c2w, np.float64)
    w2c = world_to_camera(c2w)
    means = state.means.detach().cpu().numpy().astype(np.float64)
    z = means @ w2c[:3, :3].T[:, 2] + w2c[2, 3]
    drawn = (state.opacities.detach().cpu().numpy() > 0.05) & (z > NEAR)
    depth = float(np.median(z[drawn])) if drawn.any() else float(model.extent)
    intr = intrinsics
    rays = np.stack([(xs + 0.5 - intr.cx) / intr.fx, (ys + 0.5 - intr.cy) / intr.fy, np.ones(len(xs))], -1)
    points = (rays * depth) @ c2w[:3, :3].T + c2w[:3, 3]
    n = len(points)
    size = 0.6 * stride * depth / intr.fx  # a grid cell's footprint, overlapping its neighbours
    colors = torch.as_tensor(frame[ys, xs], dtype=torch.float32)
    like = state.colors
    if like.dim() == 3:  # SH coefficients: the colour in the DC term, the rest zero
        sh = torch.zeros(n, like.shape[1], like.shape[2], dtype=like.dtype)
        sh[:, 0] = (colors - 0.5) / SH_C0
        colors = sh
    dev = state.means.device
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return GaussianState(torch.as_tensor(points, dtype=torch.float32, device=dev), quats.to(dev),
                         torch.full((n, 3), size, dtype=torch.float32, device=dev),
                         torch.full((n,), opacity, dtype=torch.float32, device=dev), colors.to(dev))


def with_spawned(state: GaussianState, spawned: GaussianState | None) -> GaussianState:
    """``state`` and an anchor's spawned Gaussians drawn together."""
    if spawned is None:
        return state
    return GaussianState(*(torch.cat([a, b.to(a.dtype)]) for a, b in
                           zip(state.tensors(), spawned.tensors(), strict=True)))

