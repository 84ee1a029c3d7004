"""EdMCGS: canonical Gaussians moved by control points whose state is an event-driven Markov chain.

At a query time t, control point j moves by

    delta_mu_j(t) = f_theta(gamma(sg(mu_j)), gamma(t))  +  s * g_phi(gamma(mu_j), m_j(t))
                    (RGB prior)                            (event transition, from I_E over [tau(t), t))

and linear blend skinning carries the Gaussians along. ``s`` is the warm-in scale (1 after training).
This module holds the state and the inference API; training lives in ``edmcgs.model.train.trainer``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from edmcgs.errors import InvalidInputError, RenderError, translated
from edmcgs.geometry import Intrinsics, Trajectory, project, quat_normalize, validate_pose, world_to_camera
from edmcgs.luminance import LUMA
from edmcgs.model.config import EdmcgsConfig
from edmcgs.model.motion.background import BackgroundLayer, composite
from edmcgs.model.motion.control_points import ControlPoints
from edmcgs.model.motion.deformation import DeformationField
from edmcgs.model.motion.event_branch import EventEncoder, EventTransition, sample_global, sample_local
from edmcgs.model.motion.gaussians import STATIC, Gaussians, GaussianState
from edmcgs.model.motion.initialization import (
    POINT_OPACITY,
    backproject_anchors,
    median_depth,
    point_gaussians,
    scene_center_and_extent,
)
from edmcgs.model.motion.leanness import bound_reach, choose_sh_degree, control_reach, motion_bound
from edmcgs.model.motion.skin_plan import SkinPlan, build_plan, plan_key, skin
from edmcgs.model.motion.skinning import identity_rotations, lbs, skinning_weights
from edmcgs.model.motion.windows import WindowIndex, WindowRows
from edmcgs.model.render.rasterize import rasterize

NEAR = 0.01
"""Control points closer than this to the event camera (or behind it) read a zero motion code."""
DRAWN_PLANS = 4
"""Windows whose ``drawn_plan`` a model keeps at least (the server's renders are mostly near the head) ..."""
DRAWN_PLANS_BYTES = 128 << 20
"""... and more while their plans hold no more than this: a viewer scrubbing a recording's span rebuilds
none (street3d: 21 windows, 13 MB; a build cost a sweep's render 0.9 ms)."""
ANCHOR_PRIORS = 64
"""(Anchor, control points) whose prior a model keeps (``_prior_since``: a few KB each)."""


@dataclass
class SceneMeta:
    """What a checkpoint knows about its scene (everything a server needs besides the weights)."""

    t_start_us: int
    """Start of the trained span (the first anchor), absolute microseconds."""
    t_end_us: int
    """End of the trained span, absolute microseconds (> t_start_us)."""
    anchors_us: np.ndarray
    """[F] int64 strictly increasing anchor (RGB frame) times, microseconds."""
    intrinsics: Intrinsics
    """The camera of the anchor frames (pixels)."""
    event_width: int
    """Width of the event maps the model takes (the event camera's resolution)."""
    event_height: int
    """Height of the event maps."""
    trajectory: Trajectory | None
    """Event-camera camera-to-world over time (the recording's trajectory, or the anchors' poses)."""
    channels: int
    """Colour channels of renders: 1 (grey) or 3 (RGB)."""
    config: dict
    """The training configuration (``EdmcgsConfig.to_dict()``)."""
    has_event_branch: bool
    """Whether the event-driven transition exists (config events and markov)."""
    frozen: np.ndarray | None = None
    """[M] bool control points whose motion over the whole span stays below ``freeze_threshold``
    (decided when the checkpoint is finalised, ``leanness.frozen_control_points``); None: none."""
    freeze_threshold: float = 0.0
    """World units: the most a frozen control point moves any of its Gaussians over the span."""
    lean: dict | None = None
    """What was left out of this scene and why (``leanness.decisions``), JSON-able; None: unknown."""

    @property
    def event_intrinsics(self) -> Intrinsics:
        """The same camera at the event map's resolution."""
        if (self.event_width, self.event_height) == (self.intrinsics.width, self.intrinsics.height):
            return self.intrinsics
        return self.intrinsics.scaled(self.event_width, self.event_height)

    def normalized_time(self, t_us: int) -> float:
        """t in [0, 1] over the trained span (exact integer arithmetic, then one rounding), clamped."""
        frac = (int(t_us) - self.t_start_us) / (self.t_end_us - self.t_start_us)
        return float(min(max(frac, 0.0), 1.0))


class EdMCGS(nn.Module):
    """The dynamic scene. Build with ``from_arrays`` (untrained) or ``checkpoint.load_checkpoint``."""

    def __init__(self, meta: SceneMeta, config: EdmcgsConfig, gaussians: Gaussians, control: ControlPoints,
                 center: Tensor, extent: float, bg_layer: BackgroundLayer | None = None):
        super().__init__()
        self.meta = meta
        self.config = config
        self.gaussians = gaussians
        self.control = control
        self.prior = DeformationField(width=config.deform_width, depth=config.deform_depth,
                                      pos_freqs=config.pos_freqs, time_freqs=config.time_freqs)
        if config.has_event_branch:
            # The largest log-luminance change of a pixel with I in [0, 1]: log(1 + eps) - log(eps).
            self.encoder = EventEncoder(limit=math.log1p(1.0 / config.log_eps), pool=config.event_pool,
                                        act=config.event_act)
            self.transition = EventTransition(pos_freqs=config.event_pos_freqs, hidden=config.event_hidden)
        else:
            self.encoder = None
            self.transition = None
        self.bg_layer = bg_layer
        """The distant background layer (config.bg_layer), or None: the constant ``background``."""
        self.online_transition: EventTransition | None = None
        """The transition online anchors use past the span, distilled from this model's own motion
        (``model/online/distill.py``); None: g_phi as trained."""
        self.register_buffer("center", center.float().reshape(3))
        self.register_buffer("extent", torch.tensor(float(extent)))
        self.register_buffer("event_scale", torch.tensor(1.0))
        self._plans: dict[bool, SkinPlan] = {}
        self.skinning = lbs
        """The skinning of ``state_from_motion``: ``lbs``, or the same compiled by ``torch.compile``
        (``Trainer(compile=True)``, ``edmcgs train --compile``)."""
        self.compiled_event_motion = None
        """torch.compile's ``event_motion``, which training calls in its place (``Trainer(compile=True)``)."""
        self._window_plans: dict[tuple[int, bool], SkinPlan] = {}
        self._drawn_plans: dict[tuple[int, bool], SkinPlan] = {}
        self._anchor_priors: dict[tuple, tuple[Tensor, Tensor]] = {}
        self._windows: WindowIndex | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(cls, *, anchors_t_us: np.ndarray, anchor_images: np.ndarray, intrinsics: Intrinsics,
                    anchor_poses: np.ndarray | None = None, t_end_us: int | None = None,
                    trajectory: Trajectory | None = None, event_size: tuple[int, int] | None = None,
                    config: EdmcgsConfig | None = None, init_depth: float = 1.0,
                    points_xyz: np.ndarray | None = None, points_colors: np.ndarray | None = None) -> EdMCGS:
        """An untrained model initialised from a recording's anchor frames (on the CPU).

        anchors_t_us: np.ndarray   # [F] int64, strictly increasing, microseconds
        anchor_images: np.ndarray  # [F, H, W, C] uint8, C = 1 or 3, H, W = intrinsics' size
        anchor_poses: np.ndarray   # [F, 4, 4] float64 c2w; None: a static camera at the origin
        t_end_us: end of the span (default: the last anchor; must be > the first anchor)
        trajectory: event-camera c2w over time (default: the anchors' poses)
        event_size: (width, height) of the event maps (default: the image size)
        init_depth: scene depth when the anchors' optical axes do not meet (world units; with points,
                    their median depth in the anchors' views)
        points_xyz: np.ndarray     # [P, 3] float64 3D points of the static scene (structure from motion's)
        points_colors: np.ndarray  # [P, C] uint8 their colours; both needed by config.static_set
        """
        config = config or EdmcgsConfig()
        config.validate()
        t = _int64_times(anchors_t_us, "anchors_t_us")
        images = np.asarray(anchor_images)
        if (images.dtype != np.uint8 or images.ndim != 4 or images.shape[0] != t.shape[0]
                or images.shape[3] not in (1, 3)):
            raise InvalidInputError(f"anchor_images must be uint8 [F={t.shape[0]}, H, W, 1|3], got "
                                    f"{images.dtype} {images.shape}")
        if (images.shape[2], images.shape[1]) != (intrinsics.width, intrinsics.height):
            raise InvalidInputError(f"anchor_images are {images.shape[2]}x{images.shape[1]} but the "
                                    f"intrinsics say {intrinsics.width}x{intrinsics.height}")
        if anchor_poses is None:
            poses = np.repeat(np.eye(4)[None], t.shape[0], axis=0)
        else:
            poses = np.asarray(anchor_poses, dtype=np.float64)
            if poses.shape != (t.shape[0], 4, 4):
                raise InvalidInputError(f"anchor_poses must be [{t.shape[0]}, 4, 4], got {poses.shape}")
            for pose in poses:
                validate_pose(pose)
        t_end = int(t[-1]) if t_end_us is None else int(t_end_us)
        if t_end <= int(t[0]):
            raise InvalidInputError(f"t_end_us={t_end} must be after the first anchor {int(t[0])} "
                                    "(a span needs at least two anchors or a later end time)")
        if not math.isfinite(init_depth) or init_depth <= 0:
            raise InvalidInputError(f"init_depth must be a positive number, got {init_depth}")
        if config.static_set:
            if points_xyz is None or points_colors is None or len(points_xyz) < 4:
                raise InvalidInputError("config.static_set starts the static set on the recording's 3D "
                                        "points and it has none: estimate them with the poses (--poses auto)")
            if np.shape(points_colors) != (len(points_xyz), images.shape[3]):
                raise InvalidInputError(f"points_colors must be [{len(points_xyz)}, {images.shape[3]}] (the "
                                        f"frames' channels), got {np.shape(points_colors)}")
            init_depth = median_depth(points_xyz, poses) or init_depth
        ew, eh = event_size or (intrinsics.width, intrinsics.height)
        if trajectory is None:
            trajectory = Trajectory(t.copy(), poses.copy())
        meta = SceneMeta(t_start_us=int(t[0]), t_end_us=t_end, anchors_us=t, intrinsics=intrinsics,
                         event_width=int(ew), event_height=int(eh), trajectory=trajectory,
                         channels=int(images.shape[3]), config=config.to_dict(),
                         has_event_branch=config.has_event_branch)

        torch.manual_seed(config.seed)
        rng = np.random.default_rng(config.seed)
        center, extent = scene_center_and_extent(poses, intrinsics, init_depth)
        # The SH degree the views can constrain (leanness.py), recorded with the reason.
        degree, record = choose_sh_degree(np.concatenate([poses, trajectory.c2w]), center, config.sh_degree)
        config = config.replace(sh_degree=degree)
        meta.config, meta.lean = config.to_dict(), {"sh_degree": record}
        k = config.init_anchors or len(images)
        layer = None
        background = background_color(config, images.shape[3]).numpy()
        if config.bg_layer:
            layer = BackgroundLayer.covering(np.concatenate([poses[:, :3, :3], trajectory.c2w[:, :3, :3]]),
                                             intrinsics, int(images.shape[3]))
            layer.fit_median(images, poses[:, :3, :3], intrinsics)
            with torch.no_grad():
                background = np.stack([layer.image(p[:3, :3], intrinsics).numpy() for p in poses[:k]])
        if config.static_set:  # the static set on the points; what moves is lifted in training
            points, colors, scales = point_gaussians(points_xyz, points_colors, extent)
            gaussians = Gaussians.from_points(points, colors, scales, sh_degree=config.sh_degree,
                                              opacity=POINT_OPACITY,
                                              birth=torch.full((len(points),), STATIC, dtype=torch.long))
        else:
            points, colors, scales, views = backproject_anchors(
                images[:k], poses[:k], intrinsics, center, extent, config.initial_points(k), rng, background,
                threshold=config.dynamic_threshold, return_views=True)
            gaussians = Gaussians.from_points(points, colors, scales, sh_degree=config.sh_degree,
                                              opacity=config.init_opacity,
                                              birth=views if config.anchor_windows else None)
        m = min(config.control_points(k), len(gaussians))
        control = ControlPoints.sample(gaussians.means.detach(), m, skin_k=config.skin_k,
                                       graph_k=config.graph_k, radius=config.radius_init * extent,
                                       birth=gaussians.birth)
        model = cls(meta, config, gaussians, control, torch.from_numpy(center), extent, layer)
        model.event_scale.fill_(0.0 if config.has_event_branch else 1.0)
        return model.eval()

    # ------------------------------------------------------------------ time
    def tau(self, t_us: int) -> int:
        """The last anchor time <= t_us (microseconds); ``InvalidInputError`` before the first anchor."""
        t_us = _int_time(t_us, "t_us")
        anchors = self.meta.anchors_us
        if t_us < int(anchors[0]):
            raise InvalidInputError(f"t_us={t_us} is before the first anchor ({int(anchors[0])}): "
                                    "the Markov chain has no state there")
        return int(anchors[np.searchsorted(anchors, t_us, side="right") - 1])

    def window(self, t_us: int) -> int | None:
        """The anchor index whose Gaussians are drawn at ``t_us`` (config.anchor_windows), else None."""
        if self.gaussians.birth is None:
            return None
        return self._anchor_index(self.tau(t_us))

    def _anchor_index(self, anchor_us: int) -> int:
        return int(np.searchsorted(self.meta.anchors_us, anchor_us, side="left"))

    def _anchor(self, anchor_us: int, t_us: int) -> int:
        """``anchor_us`` checked to be one of the checkpoint's anchors at or before ``t_us``."""
        anchor_us = _int_time(anchor_us, "anchor_us")
        anchors = self.meta.anchors_us
        i = self._anchor_index(anchor_us)
        if anchor_us > t_us or i == len(anchors) or int(anchors[i]) != anchor_us:
            raise InvalidInputError(f"anchor_us={anchor_us} is not one of the checkpoint's anchors at or "
                                    f"before t_us={t_us}")
        return anchor_us

    # ------------------------------------------------------------------ differentiable core
    def normalize_points(self, points: Tensor) -> Tensor:
        """World points -> scene coordinates (centre 0, extent 1), the networks' input frame."""
        return (points - self.center) / self.extent

    @property
    def windowed(self) -> bool:
        """Anchor windows and no static set: ``deform`` at t skins one window's rows (``window_plan``, one
        kept per window). With a static set, drawn in every window and skinned by none, it cuts the model
        to the static set and the window's (``drawn_plan``: the few plans queried last are kept, each
        holding a copy of the static set). A training step draws ``window_rows(w).drawn`` either way, of the
        static set what its cameras can see (``motion.windows.with_static``)."""
        return self.gaussians.birth is not None and not self.config.static_set

    def window_rows(self, window: int) -> WindowRows:
        """The rows of anchor ``window`` (config.anchor_windows): its Gaussians and the control points they
        need (``motion.windows``); built once per binding."""
        g, cp = self.gaussians, self.control
        if g.birth is None or cp.birth is None:
            raise InvalidInputError("the model has no anchor windows (config.anchor_windows)")
        key = plan_key(g.birth, cp.birth, cp.bind, cp.graph)
        if self._windows is None or self._windows.key != key:
            self._windows = WindowIndex(key)
        return self._windows.rows(int(window), g.birth, cp.birth, cp.bind, cp.graph)

    def control_motion(self, t: float, event_map: Tensor | None = None, ev_w2c: Tensor | None = None, *,
                       static: bool = False, since: float | None = None,
                       nonzero: bool | None = None, window: int | None = None,
                       points: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
        """Control-point transforms at normalised time ``t``.

        event_map: Tensor  # [He, We] float32 signed polarity sum over [tau(t), t), or None (empty)
        ev_w2c: Tensor     # [4, 4] event camera world-to-camera at t (needed by local sampling)
        static: the identity motion (warm-up of the canonical set)
        since: normalised time of the anchor the motion starts from (anchor windows): the prior's motion
               is taken relative to it, f(x, t) - f(x, since), so the state at the anchor is canonical
        nonzero: whether ``event_map`` has a non-zero entry, when the caller knows it (training's event
                 grid does); None: looked at here, which on a GPU waits for the device
        window: with anchor windows, only that window's control points (``window_rows(window).control``,
               in that order), moved since its anchor (unless ``since`` says otherwise)
        points: only these control points (int64 indices, in that order): the ones a render moves
        returns (translations [M, 3], rotations [M, 4] unit, event displacement [M, 3] or None)
        """
        rows = points
        if window is not None and self.gaussians.birth is not None:
            rows = self.window_rows(window).control
            if since is None:
                since = self.meta.normalized_time(int(self.meta.anchors_us[window]))
        cp = self.control.positions if rows is None else self.control.positions[rows]
        if static:
            return torch.zeros_like(cp), identity_rotations(cp.shape[0], device=cp.device), None
        x = self.normalize_points(cp)
        d_mu, d_q = self.prior(x, t)
        if since is not None:
            if torch.is_grad_enabled():
                d_mu0, d_q0 = self.prior(x, since)
            else:
                d_mu0, d_q0 = self._prior_since(x, since, rows)
            d_mu, d_q = d_mu - d_mu0, d_q - d_q0
        trans = d_mu * self.extent
        rot = quat_normalize(identity_rotations(cp.shape[0], device=cp.device) + d_q)
        event_disp = None  # (none for no points: a window before the moving preset's lift has none)
        if self.transition is not None and event_map is not None and cp.shape[0] > 0 and (
                bool(torch.any(event_map != 0)) if nonzero is None else nonzero):
            if self.config.local_sampling and ev_w2c is None:
                raise InvalidInputError("ev_w2c is needed to project control points on the event camera")
            compiled = self.compiled_event_motion if torch.is_grad_enabled() else None
            event_disp = (compiled or self.event_motion)(event_map, x, (cp + trans).detach(), ev_w2c)
            trans = trans + event_disp
        return trans, rot, event_disp

    def event_motion(self, event_map: Tensor, x: Tensor, moved: Tensor, ev_w2c: Tensor | None) -> Tensor:
        """g_phi's displacement [M, 3] (world units) of the control points ``x`` (normalised) from
        ``event_map`` [He, We], each point's motion code read where the prior has moved it (``moved``
        [M, 3], world; ``ev_w2c`` the event camera) unless config.local_sampling is off. One pure function
        of tensors: training calls ``compiled_event_motion``, torch.compile's, where it is set."""
        feats = self.encoder(self.config.contrast_threshold * event_map[None, None])[0]
        if self.config.local_sampling:
            intr = self.meta.event_intrinsics
            uv, depth = project(moved, ev_w2c, intr)
            codes = sample_local(feats, uv, depth > NEAR, intr.width, intr.height)
        else:
            codes = sample_global(feats, x.shape[0])
        return self.transition(x, codes) * (self.extent * self.event_scale)

    def _prior_since(self, x: Tensor, since: float, rows: Tensor | None) -> tuple[Tensor, Tensor]:
        """``prior(x, since)``, ``x`` the control points ``rows`` (None: all) normalised: the prior at an
        anchor, the same for every query in its gap, so kept for the last ``ANCHOR_PRIORS`` (anchor, rows)
        where no gradient is wanted (half the prior's work of a render); keyed by the rows' values (a few
        dozen indices) and by what the prior is computed from, as the plans are."""
        key = (since, None if rows is None else rows.cpu().numpy().tobytes(),
               *plan_key(self.control.positions, self.center, self.extent, *self.prior.parameters()))
        out = self._anchor_priors.pop(key, None)
        if out is None:
            out = self.prior(x, since)
        priors = self._anchor_priors
        priors[key] = out  # newest last
        for old in list(priors)[:-ANCHOR_PRIORS]:
            priors.pop(old, None)
        return out

    def window_state(self, trans: Tensor, rot: Tensor, window: int, *, motion_only: bool = False,
                     rows: WindowRows | None = None) -> GaussianState:
        """What is drawn in anchor ``window``'s gap, whatever the number of windows (the rows
        ``window_rows(window).drawn``, in the model's order): its Gaussians skinned by its control points'
        transforms (as ``control_motion(..., window=window)`` gives them), the static set as it stands.
        motion_only: as in ``state_from_motion``. rows: ``window_rows(window)`` with a part of the static
        set (``motion.windows.with_static``: what a training step's cameras can see)."""
        rows = self.window_rows(window) if rows is None else rows
        g, cp = self.gaussians, self.control
        canon = g.activated(rows.drawn)
        if motion_only:
            canon = [t.detach() for t in canon]
        means, quats = canon[0], canon[1]
        positions = cp.positions[rows.control]
        skinned = len(rows.skinned) < len(rows.drawn)  # a static set beside the window's own
        if skinned:
            means, quats = means[rows.skinned], quats[rows.skinned]
        weights = skinning_weights(means.detach(), positions, cp.log_radius[rows.control], rows.bind)
        means, quats = self.skinning(means, quats, positions, rot, trans, rows.bind, weights)
        if skinned:
            means = canon[0].index_copy(0, rows.skinned, means)
            quats = quat_normalize(canon[1]).index_copy(0, rows.skinned, quats)
        return GaussianState(means, quats, canon[2], canon[3], canon[4])

    def state_from_motion(self, trans: Tensor, rot: Tensor, window: int | None = None, *,
                          motion_only: bool = False, weights: Tensor | None = None) -> GaussianState:
        """Skin the canonical Gaussians by control-point transforms [M, 3], [M, 4]; with anchor windows,
        ``window`` (an anchor index) zeroes the opacity of the Gaussians living in other gaps.
        motion_only: the canonical Gaussians enter detached (a loss on the result trains the motion).
        weights: ``control.weights(gaussians.means)`` when the caller already has them (a training
        step skins several times with the same parameters)."""
        g = self.gaussians
        if weights is None:
            weights = self.control.weights(g.means)
        canon = g.activated()
        if motion_only:
            canon = [t.detach() for t in canon]
        static = g.static()
        if static is None:
            means, quats = self.skinning(canon[0], canon[1], self.control.positions, rot, trans,
                                         self.control.bind, weights)
        else:  # the static set keeps its canonical pose: only the others are skinned
            moving = torch.nonzero(~static)[:, 0]
            moved, turned = self.skinning(canon[0][moving], canon[1][moving], self.control.positions, rot,
                                          trans, self.control.bind[moving], weights[moving])
            means = canon[0].index_copy(0, moving, moved)
            quats = quat_normalize(canon[1]).index_copy(0, moving, turned)
        opacities = canon[3]
        visible = g.visible_in(window)
        if visible is not None:
            opacities = opacities * visible
        return GaussianState(means, quats, canon[2], opacities, canon[4])

    def state_at(self, t: float, event_map: Tensor | None = None, ev_w2c: Tensor | None = None, *,
                 static: bool = False, window: int | None = None, weights: Tensor | None = None,
                 rows: WindowRows | None = None) -> GaussianState:
        """The (differentiable) Gaussians at normalised time ``t``; see ``control_motion``. ``window``:
        the anchor (index) whose Gaussians are drawn, moved relative to that anchor's time (with anchor
        windows only they are returned, the static set's included: ``window_state``, as are ``rows``).
        weights: as in ``state_from_motion``."""
        if window is not None and self.gaussians.birth is not None:
            trans, rot, _ = self.control_motion(t, event_map, ev_w2c, static=static, window=window)
            return self.window_state(trans, rot, window, rows=rows)
        trans, rot, _ = self.control_motion(t, event_map, ev_w2c, static=static)
        return self.state_from_motion(trans, rot, weights=weights)

    # ------------------------------------------------------------------ inference API
    @torch.no_grad()
    def deform(self, t_us: int, event_map: np.ndarray | Tensor | None = None,
               ev_c2w: np.ndarray | None = None, *, anchor_us: int | None = None) -> GaussianState:
        """The Gaussians at absolute time ``t_us`` driven by the events since the last anchor.

        event_map: [event_height, event_width] float32 signed polarity sum over [tau(t_us), t_us)
                   (None or all-zero: an empty window); ignored when the model has no event branch.
        ev_c2w: [4, 4] event-camera c2w at t_us (default: the checkpoint's trajectory at t_us).
        anchor_us: tau(t_us), the anchor the events are since, when the caller decided it (the server's
                   timebase): one of the checkpoint's anchors <= t_us; default ``tau(t_us)``.
        At an anchor time the window is empty: the event map is not read and the result is the anchor
        state. The time-independent work is done once per model (``skin_plan``); the result equals
        ``state_at`` to float32 rounding, and Gaussians bound only to frozen control points keep their
        canonical pose (within ``meta.freeze_threshold``). With anchor windows it holds the Gaussians
        drawn at ``t_us`` alone (``drawn_plan``; ``window_rows`` without a static set), in the model's
        order.
        """
        t_us = _int_time(t_us, "t_us")
        tau = self.tau(t_us) if anchor_us is None else self._anchor(anchor_us, t_us)
        # At an anchor the window [tau, t) is empty: the anchor's state, the event branch skipped.
        at_anchor = t_us == tau
        device = self.center.device
        emap = None
        if event_map is not None and self.transition is not None and not at_anchor:
            emap = torch.as_tensor(event_map).to(device=device, dtype=torch.float32)
            expected = (self.meta.event_height, self.meta.event_width)
            if tuple(emap.shape) != expected:
                raise InvalidInputError(f"event_map must be {list(expected)}, got {list(emap.shape)}")
            magnitude = float(emap.abs().sum(dtype=torch.float64))  # one pass: finite, and not all zero
            if not math.isfinite(magnitude):
                raise InvalidInputError("event_map contains NaN or Inf")
            if magnitude == 0:
                emap = None
        w2c = None
        if emap is not None and self.config.local_sampling:
            if ev_c2w is None:
                if self.meta.trajectory is None:
                    raise InvalidInputError("ev_c2w is required: this checkpoint has no camera trajectory")
                ev_c2w = self.meta.trajectory.at(t_us)  # valid by construction
            else:
                validate_pose(np.asarray(ev_c2w, dtype=np.float64), name="ev_c2w")
            w2c = torch.as_tensor(world_to_camera(np.asarray(ev_c2w, dtype=np.float64)),
                                  dtype=torch.float32, device=device)
        window = None if self.gaussians.birth is None else self._anchor_index(tau)
        t = self.meta.normalized_time(t_us)
        if window is not None and self.windowed:  # that window's Gaussians alone: one window's work
            trans, rot, _ = self.control_motion(t, emap, w2c, window=window)
            own = self.window_rows(window).own  # the other windows' points: their own windows decide
            lean = False
            if self.meta.frozen is not None:
                plan = self.window_plan(window, frozen=True)
                f = plan.frozen[:own]
                lean = bool((motion_bound(trans[:own][f], rot[:own][f], plan.reach[:own][f])
                             <= self.meta.freeze_threshold).all())
            plan = self.window_plan(window, frozen=lean)
            return skin(plan, self.control.positions[self.window_rows(window).control], rot, trans)
        since = None if window is None else self.meta.normalized_time(tau)
        if window is None:
            trans, rot, _ = self.control_motion(t, emap, w2c, since=since)
        else:  # the control points the drawn Gaussians bind alone (and the window's frozen ones, below)
            points = self.drawn_plan(window, frozen=False).points
            if self.meta.frozen is not None:
                own = torch.nonzero(self._frozen_mask() & (self.control.birth == window))[:, 0]
                points = torch.unique(torch.cat([points, own]))
            m, dev = self.control.num_points, self.control.positions.device
            trans, rot = torch.zeros(m, 3, device=dev), identity_rotations(m, device=dev)
            if len(points):  # (a window drawing the static set alone moves nothing)
                moved, turned, _ = self.control_motion(t, emap, w2c, since=since, points=points)
                trans.index_copy_(0, points, moved)
                rot.index_copy_(0, points, turned)
        # Frozen Gaussians keep their canonical pose only while every frozen point's motion at this very
        # query (prior and events) stays within the threshold: the stated bound then holds at any time,
        # not only at the times the freeze decision sampled.
        lean = False
        if self.meta.frozen is not None:
            plan = self.skin_plan(frozen=True)
            f = plan.frozen
            if window is not None:  # the other windows' Gaussians are not drawn: their points may move
                f = f & (self.control.birth == window)
            lean = bool((motion_bound(trans[f], rot[f], plan.reach[f]) <= self.meta.freeze_threshold).all())
        plan = self.skin_plan(frozen=lean) if window is None else self.drawn_plan(window, frozen=lean)
        return skin(plan, self.control.positions, rot, trans)

    def _plan_key(self) -> tuple:
        g, cp = self.gaussians, self.control
        return (*plan_key(g.means, g.quats, g.log_scales, g.opacity_logits, g.features, cp.positions,
                          cp.log_radius, cp.bind), id(self.meta.frozen), cp.positions.device)

    def _frozen_mask(self) -> Tensor | None:
        """[M] bool: the checkpoint's frozen control points (None: none)."""
        cp = self.control
        if self.meta.frozen is None:
            return None
        if len(self.meta.frozen) != cp.num_points:
            raise InvalidInputError(f"meta.frozen marks {len(self.meta.frozen)} control points, the model "
                                    f"has {cp.num_points}")
        return torch.as_tensor(self.meta.frozen, dtype=torch.bool, device=cp.positions.device)

    def skin_plan(self, *, frozen: bool = True) -> SkinPlan:
        """The time-independent half of ``deform`` (weights, activated canonical Gaussians), built once
        and rebuilt only when a parameter it derives from changed. frozen: leave frozen points still."""
        g, cp = self.gaussians, self.control
        key = self._plan_key()
        plan = self._plans.get(frozen)
        if plan is None or plan.key != key:
            with torch.no_grad():
                mask = self._frozen_mask() if frozen else None
                canonical = GaussianState(g.means, g.quats, g.scales(), g.opacities(), g.colors())
                plan = self._plans[frozen] = build_plan(canonical, cp.bind, cp.weights(g.means), mask, key,
                                                        g.static())
                if mask is not None:
                    plan.frozen, plan.reach = mask, control_reach(self)
        return plan

    def window_plan(self, window: int, *, frozen: bool = True) -> SkinPlan:
        """``skin_plan`` of anchor ``window``'s Gaussians alone (indices local to ``window_rows``: its
        Gaussians, its control points); ``reach`` over the window's Gaussians. Built once per window."""
        key = (*self._plan_key(), window)
        plan = self._window_plans.get((window, frozen))
        if plan is None or plan.key != key:
            rows = self.window_rows(window)
            cp = self.control
            with torch.no_grad():
                mask = self._frozen_mask() if frozen else None
                local = None if mask is None else mask[rows.control]
                canonical = GaussianState(*self.gaussians.activated(rows.gaussians))
                positions = cp.positions[rows.control]
                weights = skinning_weights(canonical.means, positions, cp.log_radius[rows.control], rows.bind)
                plan = self._window_plans[(window, frozen)] = build_plan(canonical, rows.bind, weights, local,
                                                                          key)
                if local is not None:
                    plan.frozen, plan.reach = local, bound_reach(canonical.means, positions, rows.bind)
        return plan

    def drawn_plan(self, window: int, *, frozen: bool = True) -> SkinPlan:
        """``skin_plan`` cut to the Gaussians drawn in anchor ``window``'s gap (``visible_in``: the static
        set and the window's own). The others would be drawn with opacity 0: a long recording's windows
        hold most of a model's Gaussians, so leaving them out spares a render most of its work. The plans
        of the windows queried last are kept (``DRAWN_PLANS``, ``DRAWN_PLANS_BYTES``)."""
        key = (*self._plan_key(), window)
        plan = self._drawn_plans.pop((window, frozen), None)
        if plan is None or plan.key != key:
            full = self.skin_plan(frozen=frozen)
            n = len(self.gaussians)
            rows = self.window_rows(window).drawn
            # full.bind and full.weights hold the skinned rows alone, in full.moving's order
            dev = rows.device
            slot = torch.arange(n, device=dev)
            if full.moving is not None:
                slot = torch.full((n,), -1, dtype=torch.long, device=dev).index_copy_(
                    0, full.moving, torch.arange(len(full.moving), device=dev))
            slot = slot[rows]
            moving = torch.nonzero(slot >= 0)[:, 0]
            c = full.canonical
            canonical = GaussianState(c.means[rows], c.quats[rows], c.scales[rows], c.opacities[rows],
                                      c.colors[rows])
            bind = full.bind[slot[moving]]
            plan = SkinPlan(canonical, bind, full.weights[slot[moving]],
                            None if len(moving) == len(rows) else moving, key, full.frozen, full.reach,
                            torch.unique(bind))
        plans = self._drawn_plans
        plans[(window, frozen)] = plan  # newest last
        kept = list(plans.items())  # one call each: safe beside a render in another thread
        held = sum(p.nbytes for _, p in kept)
        for old, p in kept[:-DRAWN_PLANS]:
            if held <= DRAWN_PLANS_BYTES:
                break
            plans.pop(old, None)
            held -= p.nbytes
        return plan

    @torch.no_grad()
    def render(self, state: GaussianState, c2w: np.ndarray, intrinsics: Intrinsics, *, fast: bool = True,
               background: np.ndarray | float | None = None, threads: int | None = None) -> np.ndarray:
        """Render ``state`` from camera ``c2w`` [4, 4] (OpenCV c2w) -> [H, W, C] float32 in [0, 1].

        fast: the forward-only numba CPU rasterizer; False: the differentiable one (``rasterize``:
              numba kernels on the CPU, torch elsewhere; same image to ~1e-5).
        background: grey level or [C] colour behind the Gaussians (default: the background layer when
                    the model has one, else the config's colour).
        threads: the fast rasterizer's threads (default: numba's, all cores); a server running several
                 renders at once on a few shared cores is faster with 1 each (no parallel-region stalls).
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        validate_pose(c2w)
        w2c = world_to_camera(c2w)
        layer = self.bg_layer if background is None else None
        bg = np.zeros(self.meta.channels, np.float32) if layer is not None else self._background(background)
        with _render_errors():
            if fast:
                out = _rasterize_fast(state, w2c, intrinsics, bg, threads, alpha=layer is not None)
                image = out.image
                if layer is not None:
                    behind = layer.image(c2w[:3, :3], intrinsics).detach().cpu().numpy()
                    image = image + (1.0 - out.alpha)[..., None] * behind
            else:
                dev = state.means.device
                behind = None if layer is None else layer.image(c2w[:3, :3], intrinsics)
                # the camera as host float32 (the values a device tensor would hold): nothing read back
                image = render_image(state, w2c.astype(np.float32), intrinsics,
                                     torch.as_tensor(bg, device=dev), behind).cpu().numpy()
        image = image.astype(np.float32, copy=False)
        if not np.isfinite(image).all():  # checked first: nan_to_num costs 10x the check
            image = np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0)
        return np.clip(image, 0.0, 1.0, out=image)

    @torch.no_grad()
    def render_depth_alpha(self, state: GaussianState, c2w: np.ndarray, intrinsics: Intrinsics, *,
                           fast: bool = True, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The splats of ``state`` seen from ``c2w`` as two float32 [H, W] maps: the expected depth along
        the camera's z, sum_i w_i z_i / sum_i w_i over the splats blended into each pixel (w_i = alpha_i
        T_i; 0 where none is), and the accumulated opacity 1 - T. A background layer is not in them (it
        is no set of Gaussians). fast, threads: as ``render``."""
        c2w = np.asarray(c2w, dtype=np.float64)
        validate_pose(c2w)
        w2c = world_to_camera(c2w)
        bg = np.zeros(self.meta.channels, np.float32)
        with _render_errors():
            if fast:
                out = _rasterize_fast(state, w2c, intrinsics, bg, threads, alpha=True, depth=True)
                depth, alpha = out.depth, out.alpha
            else:
                dev = state.means.device
                out = rasterize(*state.tensors(), w2c.astype(np.float32), intrinsics, return_depth=True,
                                background=torch.as_tensor(bg, device=dev), return_alpha=True)
                depth, alpha = out.depth.cpu().numpy(), out.alpha.cpu().numpy()
        depth = np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        alpha = np.nan_to_num(alpha.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        return np.maximum(depth, 0.0, out=depth), np.clip(alpha, 0.0, 1.0, out=alpha)

    def _background(self, background) -> np.ndarray:
        c = self.meta.channels
        if background is None:
            return background_color(self.config, c).numpy()
        bg = np.asarray(background, dtype=np.float32).reshape(-1)
        if bg.size == 1:
            bg = np.repeat(bg, c)
        if bg.size != c or not np.all(np.isfinite(bg)):
            raise InvalidInputError(f"background must be a number or {c} finite numbers, got {background!r}")
        return bg


def _render_errors():
    """A rasterizer's RuntimeError / ValueError as a RenderError (our InvalidInputError kept)."""
    return translated((RuntimeError, ValueError), lambda exc: RenderError(f"rendering failed: {exc}"),
                      keep=InvalidInputError)


def _rasterize_fast(state: GaussianState, w2c: np.ndarray, intrinsics: Intrinsics, background: np.ndarray,
                    threads: int | None, *, alpha: bool = False, depth: bool = False):
    """``rasterize_fast`` of ``state`` (numpy RenderOutput), torch's thread count kept."""
    # Imported here: the forward-only numba renderer is for serving.
    from edmcgs.model.render.rasterize_fast import rasterize_fast

    arrays = [t.detach().cpu().numpy() for t in state.tensors()]
    torch_threads = torch.get_num_threads()
    try:
        return rasterize_fast(*arrays, w2c.astype(np.float32), intrinsics, background=background,
                              threads=threads, return_alpha=alpha, return_depth=depth)
    finally:
        # numba's OpenMP layer sets the process-wide OpenMP thread count, which is also torch's; put
        # back what the caller chose.
        torch.set_num_threads(torch_threads)


def background_color(config: EdmcgsConfig, channels: int) -> Tensor:
    """[C] float32 background of renders: the config's RGB, or its Rec. 601 luma for grey."""
    rgb = torch.tensor(config.background, dtype=torch.float32)
    return rgb if channels == 3 else (rgb @ torch.tensor(LUMA)).reshape(1)


def render_image(state: GaussianState, w2c: Tensor | np.ndarray, intrinsics: Intrinsics, background: Tensor,
                 layer: Tensor | None = None) -> Tensor:
    """Differentiable render of ``state`` -> [H, W, C] (the training path); ``layer`` [H, W, C]: the
    background layer's view, composited under the splats instead of ``background``. ``w2c`` on the host
    spares a GPU's render the read back of its camera."""
    if layer is None:
        return rasterize(*state.tensors(), w2c, intrinsics, background=background).image
    out = rasterize(*state.tensors(), w2c, intrinsics, background=torch.zeros_like(background),
                    return_alpha=True)
    return composite(out.image, out.alpha, layer)



def _int_time(t_us, name: str) -> int:
    if isinstance(t_us, bool) or not isinstance(t_us, (int, np.integer)):
        raise InvalidInputError(f"{name} must be integer microseconds, got {type(t_us).__name__}")
    return int(t_us)


def _int64_times(values, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1 or arr.shape[0] == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise InvalidInputError(f"{name} must be a non-empty 1-D integer array (microseconds), got "
                                f"{arr.dtype} {arr.shape}")
    arr = arr.astype(np.int64)
    if np.any(np.diff(arr) <= 0):
        raise InvalidInputError(f"{name} must be strictly increasing")
    return arr
