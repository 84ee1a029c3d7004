"""An online anchor's state and its Markov transition: the control-point motion at an anchor past the
span, moved by the events since it (the package's docstring has the formulas), and the Gaussians it
skins."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import project, world_to_camera
from edmcgs.model.dynamic import NEAR, EdMCGS
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


def with_spawned(state: GaussianState, spawned: GaussianState | None) -> GaussianState:
    """``state`` and an anchor's spawned Gaussians drawn together."""
    if spawned is None:
        return state
    return GaussianState(*(torch.cat([a, b.to(a.dtype)]) for a, b in
                           zip(state.tensors(), spawned.tensors(), strict=True)))

