"""Fitting an online anchor to its frame: the correction (a motion residual and colour offsets), how
well candidate predictions explain a frame, the transition's fine-tune, and the Gaussians spawned for
what the frame shows that the carried-forward window lacks."""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import Tensor

from edmcgs.geometry import Intrinsics, world_to_camera
from edmcgs.model.dynamic import NEAR, EdMCGS, background_color, render_image
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.online.transition import (
    Motion,
    last_window,
    motion_codes,
    recolored,
    state_of,
    with_spawned,
)
from edmcgs.model.render.sh import SH_C0


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
