"""One configuration for EdMCGS, in four parts: structure, initialisation, losses and schedule.

``EdmcgsConfig`` is composed of the parts (a dataclass deriving from each), so every field reads flat
(``cfg.skin_k``), ``--set key=value`` takes flat keys, and a checkpoint stores the config as one flat map
(the format every checkpoint has had). What a part is decides what a resume may change: ``Structure`` and
``Initialisation`` describe the saved tensors, so ``frozen_changes`` names them for ``--resume`` to refuse;
``Losses`` and ``Schedule`` only steer further training.

The ablations of the paper are switches, never copies of code: ``events=False`` (time-only prior),
``markov=False`` (events only as a training loss), ``local_sampling=False`` (global average pooling of
the event features), ``tli=False``. Schedules are fractions of the run's steps (``iterations``, or
``steps_per_window`` times the spans between anchors: ``total_steps``) so that either keeps them
consistent.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

from edmcgs.errors import InvalidInputError, did_you_mean
from edmcgs.luminance import LOG_EPS


@dataclass
class Structure:
    """What the checkpoint's tensors are: which exist (the switches), their sizes, and the constants the
    trained model computes with (Phi's input scale and activation, the colour behind the Gaussians).
    The model is built from these; a resumed run keeps the saved tensors, so it cannot change them."""

    events: bool = True
    """Use the event stream at all. False: the time-only prior, no event loss, no event branch."""
    markov: bool = True
    """Event-driven Markov transition g_phi, active at inference. False: events only supervise."""
    local_sampling: bool = True
    """Sample Phi's map at each control point's projection. False: one globally pooled code."""
    sh_degree: int = 0
    """Spherical-harmonics degree of the colour; 0 stores a plain colour per Gaussian."""
    num_control_points: int = 512
    """M: control points sampled by farthest-point sampling of the canonical means."""
    control_points_per_window: int = 0
    """With anchor windows: M = this many times the number of anchors (farthest-point sampling gives each
    window about this many), so that a longer recording keeps as many per window, and never fewer than
    num_control_points (a short recording keeps what it had); 0: num_control_points."""
    skin_k: int = 3
    """K: control points each Gaussian is bound to (linear blend skinning)."""
    graph_k: int = 10
    """K_conn: neighbours of each control point in the TLI / smoothness graph."""
    deform_width: int = 256
    """Width of the RGB-prior deformation MLP f_theta."""
    deform_depth: int = 8
    """Hidden layers of f_theta (a skip connection re-injects the input half-way)."""
    pos_freqs: int = 10
    """Positional-encoding frequencies of a control point's position for f_theta."""
    time_freqs: int = 6
    """Positional-encoding frequencies of the normalised time for f_theta."""
    event_pos_freqs: int = 4
    """Positional-encoding frequencies of the control point's position for g_phi."""
    event_hidden: int = 64
    """Hidden width of g_phi."""
    event_pool: int = 1
    """Phi reads I_E averaged over pool x pool pixel blocks (1: full resolution, as in the paper)."""
    event_act: str = "relu"
    """Activation of Phi's hidden layers: ``relu`` (the paper's) or ``leaky`` (LeakyReLU 0.1; a channel
    cannot die). Both keep Phi(0) = 0."""
    bg_layer: bool = False
    """A distant background layer (``motion.background``): a learned texture over ray directions,
    initialised from the anchors' per-texel median, behind the Gaussians instead of ``background``.
    For a static or rotating camera (the static scene at infinity); the Gaussians then model what moves."""
    anchor_windows: bool = False
    """Each Gaussian lives in the gap after the anchor it was lifted from: at time t only the Gaussians
    of tau(t)'s anchor are drawn, moved from that anchor by the prior and the events since (a Markov
    chain restarted at every anchor). Off: every Gaussian at every time."""
    static_set: bool = False
    """A static set of Gaussians besides the anchor windows' (needs ``anchor_windows``): drawn at every
    time and never moved, for what stands still in front of a moving camera. It starts on the recording's
    3D points (structure from motion's: ``--poses auto``); the windows' Gaussians are lifted in training
    (``lift_at``) from the anchor pixels it does not explain: what moves."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Linear RGB colour behind all Gaussians, in [0, 1] (grey models use its Rec. 601 luma)."""
    contrast_threshold: float = 0.2
    """C: log-luminance change per event (taken from the recording when it states one); the event loss's
    unit, and the scale of I_E that Phi reads."""
    log_eps: float = LOG_EPS
    """epsilon of the log-luminance L = log(I + epsilon), I in [0, 1]; it also bounds Phi's input."""

    @property
    def has_event_branch(self) -> bool:
        """Whether the event-driven transition (Phi, g_phi) exists."""
        return self.events and self.markov


@dataclass
class Initialisation:
    """How a new model's tensors start: read when it is built from the anchors. A resumed run keeps
    the saved tensors, so changing these would record a start the model never had."""

    init_points: int = 20000
    """Number of Gaussians at initialisation (back-projected anchor pixels; one per pixel that differs
    from the background when there are fewer such pixels)."""
    init_points_per_window: int = 0
    """With anchor windows: at most this many times the number of anchors Gaussians at initialisation (a
    longer recording keeps its density of movers), and never fewer than init_points; 0: init_points."""
    init_opacity: float = 0.1
    """Opacity of every Gaussian at initialisation."""
    init_anchors: int = 0
    """Back-project the first this many anchors at initialisation (0: all). One anchor gives a single
    canonical copy of a moving object; all give every pose, which the deformation must then hide."""
    radius_init: float = 0.1
    """Initial RBF radius of every control point, as a fraction of the scene extent."""
    dynamic_threshold: float = 2.0 / 255.0
    """Initial Gaussians go on anchor pixels that differ from the background (the colour, or the layer's
    view; with ``static_set``, the static set's render at ``lift_at``) by more than this, in [0, 1]
    intensity."""


@dataclass
class Losses:
    """The training objective: which terms are on and their weights, pyramids and pair sampling."""

    tli: bool = True
    """Temporal local isometry regulariser on the control points' KNN graph."""
    lambda_dssim: float = 0.2
    """lambda_d: weight of D-SSIM against L1 in the photometric loss at the anchors."""
    lambda_event: float = 0.05
    """lambda_e: weight of the event (EGM) loss."""
    lambda_tli: float = 1e-5
    """lambda_t: weight of the temporal local isometry loss."""
    lambda_smooth: float = 1e-2
    """lambda_s: weight of the KNN Laplacian smoothness of g_phi's output."""
    event_loss_levels: int = 1
    """Pyramid levels of the event loss (1: per pixel, as in the paper; more: also 2x, 4x ... pooled)."""
    lambda_next: float = 0.0
    """Weight of the photometric loss of a gap's Gaussians, moved by the whole gap's events (and the
    prior), against the next anchor frame (needs ``anchor_windows``). It trains the motion only: the
    canonical Gaussians enter it detached (else it would fade them rather than move them)."""
    next_levels: int = 1
    """Pyramid levels of the next-anchor loss: besides the photometric loss at full resolution, the mean
    L1 at this many - 1 coarser levels (2x, 4x ... pooled), so a mover carried to the wrong place is
    still pulled towards its next position."""
    anchored_pairs: float = 0.0
    """Probability that the event loss's first time t_a is the gap's anchor (else uniform on the grid):
    such a pair compares the render at t_b with the anchor moved on by all events since."""


@dataclass
class Schedule:
    """How training runs: steps, resolutions, event sub-steps, learning rates, density control,
    evaluation and checkpoints."""

    iterations: int = 30000
    """Optimisation steps (with steps_per_window: the fewest, those of a short recording; ``--set
    iterations=N`` alone sets steps_per_window to 0: a fixed total)."""
    steps_per_window: int = 0
    """Optimisation steps per span between two consecutive anchors: the run's steps grow with the length
    of the recording, never below ``iterations`` (``total_steps``); 0: ``iterations`` whatever the
    length."""
    train_scale: float = 1.0
    """Render and supervise at this fraction of the image resolution (the event maps fed to Phi stay
    at full resolution)."""
    event_render_scale: float = 1.0
    """The two renders of the event loss are made at this fraction of the training resolution (the
    log-luminance change is a smooth target; a coarser render costs a fraction of the time)."""
    substeps: int = 16
    """Sub-step times per gap between anchors at which event windows are pre-accumulated."""
    max_pair_steps: int = 16
    """Largest distance, in sub-steps, between the two times t_a < t_b of the event loss."""
    seed: int = 0
    """Seed of every random choice (initialisation, sampling of times)."""
    lr_means: float = 1.6e-4
    """Adam step of the canonical means, in scene extents, decayed exponentially to 1/100."""
    lr_features: float = 2.5e-3
    """Adam step of the colour (logits or SH)."""
    lr_opacity: float = 0.05
    """Adam step of the opacity logits."""
    lr_scales: float = 5e-3
    """Adam step of the log-scales."""
    lr_quats: float = 1e-3
    """Adam step of the quaternions."""
    lr_deform: float = 8e-4
    """Adam step of f_theta, decayed exponentially to 1/50."""
    lr_event: float = 1e-3
    """Adam step of Phi and g_phi, decayed exponentially to 1/10."""
    lr_background: float = 2.5e-3
    """Adam step of the background layer's texture logits."""
    lr_radius: float = 1e-3
    """Adam step of the control points' log-radii."""
    deform_from: float = 0.0
    """Fraction of training during which the deformation is off (static warm-up of the canonical set)."""
    event_warmup: tuple[float, float] = (0.2, 0.4)
    """Fractions of training between which the event branch's learning rate ramps from 0 to its own
    (before them the branch is off)."""
    max_gaussians: int = 200000
    """Densification stops adding Gaussians above this count (grown with ``init_points_per_window``:
    ``gaussian_cap``)."""
    densify_from: float = 0.02
    """Fraction of training from which adaptive density control runs."""
    densify_until: float = 0.5
    """Fraction of training after which no Gaussian is added, removed or reset."""
    densify_every: int = 100
    """Iterations between two densification steps."""
    densify_grad: float = 2e-4
    """Mean screen-space (NDC) gradient of a Gaussian's mean above which it is cloned or split."""
    percent_dense: float = 0.01
    """Gaussians smaller than this fraction of the scene extent are cloned, larger ones split."""
    prune_opacity: float = 0.005
    """Gaussians below this opacity are pruned."""
    prune_size: float = 0.1
    """Gaussians larger than this fraction of the scene extent are pruned (after the first reset)."""
    opacity_reset_every: int = 3000
    """Iterations between opacity resets (0 disables them)."""
    lift_at: float = 0.3
    """With ``static_set``: the fraction of training at which each anchor's pixels that the static set's
    render does not explain (``dynamic_threshold``) are lifted into its window, at the render's depth,
    with at most ``init_points`` over all anchors."""
    control_resample_until: float = 0.1
    """Until this fraction of training the control points are re-sampled from the current means at
    every densification step; later they are fixed (the paper's canonical control points)."""
    eval_every: int = 1000
    """Iterations between two evaluations on held-out frames (0 disables them)."""
    eval_frames: int = 8
    """Held-out frames used by the periodic evaluation (evenly spaced)."""
    checkpoint_every: int = 1000
    """Iterations between two resumable checkpoints (0: only at the end)."""


PARTS: tuple[type, ...] = (Structure, Initialisation, Losses, Schedule)
"""The config's parts, in the order ``--list-config`` and ``to_dict`` list them."""

FROZEN_PARTS: tuple[type, ...] = (Structure, Initialisation)
"""The parts that describe the saved tensors: a resumed run keeps the tensors, so it cannot change these."""

FROZEN_ON_RESUME: tuple[str, ...] = tuple(f.name for part in FROZEN_PARTS for f in fields(part))
"""The fields of ``FROZEN_PARTS``: what ``frozen_changes`` compares."""


# A dataclass lists its bases' fields from the last base to the first: the parts go in reverse so that
# fields(EdmcgsConfig) (and so repr, to_dict) read structure first, schedule last.
@dataclass
class EdmcgsConfig(Schedule, Losses, Initialisation, Structure):
    """Every knob of the model and its training, flat; presets are ``paper``, ``demo`` and ``real``."""

    def to_dict(self) -> dict:
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, data: dict) -> EdmcgsConfig:
        """Rebuild from ``to_dict`` output; unknown keys (from a newer writer) are an error."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise InvalidInputError(f"config: unknown keys {unknown}")
        cfg = cls()
        for f in fields(cls):
            if f.name in data:
                setattr(cfg, f.name, _coerce(f, data[f.name]))
        cfg.validate()
        return cfg

    def total_steps(self, anchors: int) -> int:
        """The run's steps for a recording of ``anchors`` anchor frames: ``steps_per_window`` per span
        between consecutive anchors (one span for a single anchor), at least ``iterations``."""
        if self.steps_per_window <= 0:
            return self.iterations
        return max(self.iterations, self.steps_per_window * max(int(anchors) - 1, 1))

    def control_points(self, anchors: int) -> int:
        """M for a recording of ``anchors`` anchor frames (``control_points_per_window``)."""
        if self.anchor_windows and self.control_points_per_window > 0:
            return max(self.num_control_points, self.control_points_per_window * int(anchors))
        return self.num_control_points

    def initial_points(self, anchors: int) -> int:
        """The most Gaussians at initialisation for ``anchors`` anchor frames (``init_points_per_window``)."""
        if self.anchor_windows and self.init_points_per_window > 0:
            return max(self.init_points, self.init_points_per_window * int(anchors))
        return self.init_points

    def gaussian_cap(self, anchors: int) -> int:
        """The count above which densification stops, for ``anchors`` anchor frames: ``max_gaussians``
        plus what the windows' initialisation may add beyond ``init_points`` (``initial_points``), so that
        the movers of a long recording do not take the static set's budget."""
        return self.max_gaussians + self.initial_points(anchors) - self.init_points

    def frozen_changes(self, other: EdmcgsConfig) -> list[str]:
        """The fields of ``FROZEN_ON_RESUME`` whose values differ in ``other`` (a resume's config)."""
        return [name for name in FROZEN_ON_RESUME if getattr(self, name) != getattr(other, name)]

    def replace(self, **changes) -> EdmcgsConfig:
        cfg = dataclasses.replace(self, **changes)
        cfg.validate()
        return cfg

    def with_overrides(self, items: list[str]) -> EdmcgsConfig:
        """Apply ``key=value`` strings (``--set``); values are parsed by the field's type."""
        cfg = dataclasses.replace(self)
        by_name = {f.name: f for f in fields(self)}
        pairs = split_overrides(items)
        for key, raw in pairs:
            setattr(cfg, key, _parse(by_name[key], raw))
        keys = {key for key, _ in pairs}
        if "iterations" in keys and "steps_per_window" not in keys:
            cfg.steps_per_window = 0  # a total given: fixed, whatever the recording's length
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Raise ``InvalidInputError`` naming the first field out of its range."""
        positive = ("init_points", "max_gaussians", "num_control_points", "skin_k", "graph_k",
                    "deform_width", "deform_depth", "event_hidden", "event_pool", "iterations", "substeps",
                    "event_loss_levels", "next_levels", "max_pair_steps", "densify_every", "eval_frames")
        for name in positive:
            if getattr(self, name) <= 0:
                raise InvalidInputError(f"config.{name} must be > 0, got {getattr(self, name)}")
        for name in ("init_anchors", "sh_degree", "pos_freqs", "time_freqs", "event_pos_freqs", "eval_every",
                     "checkpoint_every", "opacity_reset_every", "steps_per_window",
                     "control_points_per_window", "init_points_per_window"):
            if getattr(self, name) < 0:
                raise InvalidInputError(f"config.{name} must be >= 0, got {getattr(self, name)}")
        if self.sh_degree > 3:
            raise InvalidInputError(f"config.sh_degree must be <= 3, got {self.sh_degree}")
        for name in ("train_scale", "event_render_scale"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise InvalidInputError(f"config.{name} must be in (0, 1], got {getattr(self, name)}")
        if len(self.background) != 3 or not all(0.0 <= v <= 1.0 for v in self.background):
            raise InvalidInputError(f"config.background must be 3 numbers in [0, 1], got {self.background}")
        if self.static_set and not self.anchor_windows:
            raise InvalidInputError("config.static_set needs anchor_windows (what moves lives in them)")
        if not 0.0 <= self.lift_at < 1.0:
            raise InvalidInputError(f"config.lift_at must be in [0, 1), got {self.lift_at}")
        if not 0.0 <= self.anchored_pairs <= 1.0:
            raise InvalidInputError(f"config.anchored_pairs must be in [0, 1], got {self.anchored_pairs}")
        if self.event_act not in ("relu", "leaky"):
            raise InvalidInputError(f"config.event_act must be 'relu' or 'leaky', got {self.event_act!r}")
        if not 0.0 < self.init_opacity < 1.0:
            raise InvalidInputError(f"config.init_opacity must be in (0, 1), got {self.init_opacity}")
        if not 0.0 <= self.dynamic_threshold < 1.0:
            raise InvalidInputError(f"config.dynamic_threshold must be in [0, 1), got "
                                    f"{self.dynamic_threshold}")
        if self.lambda_next < 0:
            raise InvalidInputError(f"config.lambda_next must be >= 0, got {self.lambda_next}")
        if self.contrast_threshold <= 0 or self.log_eps <= 0 or self.radius_init <= 0:
            raise InvalidInputError("config.contrast_threshold, log_eps and radius_init must be > 0")
        lo, hi = self.event_warmup
        if not 0.0 <= lo <= hi <= 1.0:
            raise InvalidInputError(f"config.event_warmup must be 0 <= start <= end <= 1, got {lo, hi}")
        if self.skin_k > self.num_control_points or self.graph_k >= self.num_control_points:
            raise InvalidInputError("config.skin_k and graph_k must be smaller than num_control_points")


def _plain(value):
    return list(value) if isinstance(value, tuple) else value


def _coerce(f: dataclasses.Field, value):
    if f.type.startswith("tuple["):
        return tuple(float(v) for v in value)
    return value


def _parse(f: dataclasses.Field, raw: str):
    kind = f.type
    try:
        if kind == "bool":
            lowered = raw.lower()
            if lowered in ("1", "true", "yes", "on"):
                return True
            if lowered in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if kind == "int":
            return int(raw)
        if kind == "float":
            return float(raw)
        if kind.startswith("tuple["):
            parts = tuple(float(v) for v in raw.strip("()[] ").split(","))
            if len(parts) != kind.count("float"):
                raise ValueError(raw)
            return parts
    except ValueError as exc:
        raise InvalidInputError(f"--set {f.name}={raw!r}: not a valid {kind}") from exc
    return raw


def _demo() -> EdmcgsConfig:
    # Sized for a 2-core CPU and a 173x130 scene: fewer Gaussians and control points, a smaller prior,
    # 1500 iterations, the event-loss renders at half resolution. With 20x fewer steps than the paper,
    # the event loss weighs 1.0, not 0.05 (held-out PSNR rises with it up to 1.0, then the anchors lose).
    # Phi reads I_E pooled 4x4: its 23-px receptive field then spans 92 px of the event camera, the scale
    # of a limb's path between anchors, and Phi runs on a map 16x smaller. Figures:
    # docs/benchmarks/accuracy.md.
    return EdmcgsConfig(
        init_points=3000, max_gaussians=30000, num_control_points=256, deform_width=128, deform_depth=4,
        iterations=1500, train_scale=1.0, event_render_scale=0.5, eval_every=500, checkpoint_every=500,
        lr_means=4e-4, lr_deform=2e-3, lr_event=2e-3, densify_every=100, opacity_reset_every=0,
        event_warmup=(0.15, 0.3), lambda_event=1.0, event_pool=4,
    )


def _real() -> EdmcgsConfig:
    # A real sensor's street: a static (or rotating) DAVIS346 at 346x260 grey. The static scene goes to
    # the background layer; one Gaussian on every anchor pixel that differs from it (the movers: no
    # densification needed), each living in the gap after its anchor with the control points of that
    # window, and carried through the gap by the events. The motion is learnt from the event loss taken
    # from the anchor (anchored_pairs 1: the anchor state is exact, so the events since it say where the
    # edges went) plus the next anchor frame seen through a 6-level pyramid (alone, with free start
    # times, it pushes movers off the frame). Its cost follows the recording: 100 steps, 32 control
    # points and at most 3750 Gaussians per anchor window, never fewer than a 3 s clip at 5 fps has
    # (1500 steps, 512 points, 60000 Gaussians at most: a shorter recording trains as it always did).
    # Figures: docs/benchmarks/real.md, docs/benchmarks/scale.md.
    return _demo().replace(
        bg_layer=True, anchor_windows=True, event_act="leaky", dynamic_threshold=0.04, init_opacity=0.8,
        init_points=60000, max_gaussians=60000, densify_from=0.0, densify_until=0.0, steps_per_window=100,
        num_control_points=512, control_points_per_window=32, init_points_per_window=3750, skin_k=2,
        lr_features=0.01, lr_event=5e-3,
        lambda_next=1.0, next_levels=6, event_loss_levels=3, anchored_pairs=1.0, event_render_scale=1.0,
    )


def _moving() -> EdmcgsConfig:
    # A moving (translating, handheld) DAVIS346: the real preset's machinery for what moves, on top of a
    # static set of Gaussians where the real preset has its layer at infinity. The static set starts
    # on structure from motion's points (--poses auto) and is densified as in 3DGS; the background layer
    # stays for what is at infinity (the sky). After a static warm-up (lift_at), the anchor pixels the
    # static set does not explain are lifted into their anchor's window and carried through the gap by
    # the events, trained by the real preset's anchored event pairs and next-anchor loss. init_points
    # bounds the lifted Gaussians over all anchors: sized for 346x260 (street3d's 21 anchors get 2.3k to
    # 3.4k each, the order of the cars' pixels in a frame). Its cost follows the recording as the real
    # preset's does: 75 steps, 24 control points and 2857 lifted Gaussians per anchor window, never fewer
    # than street3d's 4 s has (1500 steps, 512 points, 60000 lifted: the run measured). Figures:
    # docs/benchmarks/moving.md (bench.street3d).
    return _real().replace(
        static_set=True, init_points=60000, max_gaussians=150000, densify_from=0.02, densify_until=0.6,
        steps_per_window=75, control_points_per_window=24, init_points_per_window=2857,
        densify_every=100, lift_at=0.3, init_opacity=0.8, lr_means=1.6e-4, percent_dense=0.01,
    )


PRESETS = {
    "paper": EdmcgsConfig,
    "demo": _demo,
    "real": _real,
    "moving": _moving,
}
"""Named configurations: ``paper`` (the paper's settings, 30k iterations), ``demo`` (CPU-sized),
``real`` (a static or rotating 346x260 event camera: background layer, anchor windows) and ``moving``
(a translating, handheld one with its poses and points from ``--poses auto``: a static set of Gaussians
on the points, the real preset's windows for what moves)."""


def split_overrides(items: list[str]) -> list[tuple[str, str]]:
    """``key=value`` strings (``--set``) as (key, raw value) pairs; InvalidInputError for a malformed item or
    an unknown key (with the closest known ones)."""
    known = {f.name for f in fields(EdmcgsConfig)}
    pairs = []
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep:
            raise InvalidInputError(f"--set {item!r}: expected key=value")
        if key not in known:
            raise InvalidInputError(f"--set {item!r}: unknown key {key!r}{did_you_mean(key, known)} "
                                    f"(--list-config prints all {len(known)} with their meaning)")
        pairs.append((key, raw.strip()))
    return pairs


def preset(name: str) -> EdmcgsConfig:
    """The named preset; ``InvalidInputError`` for an unknown name."""
    if name not in PRESETS:
        raise InvalidInputError(f"config: unknown preset {name!r}{did_you_mean(name, PRESETS)}; choose from "
                                f"{sorted(PRESETS)}")
    return PRESETS[name]()


def field_docs() -> dict[str, str]:
    """Each config field's description: the docstring written under it in its part."""
    import ast
    import inspect
    import itertools
    import textwrap

    docs = {}
    for part in PARTS:
        body = ast.parse(textwrap.dedent(inspect.getsource(part))).body[0].body
        for node, after in itertools.pairwise(body):
            if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr) \
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


__all__ = ["FROZEN_ON_RESUME", "FROZEN_PARTS", "PARTS", "PRESETS", "EdmcgsConfig", "Initialisation", "Losses",
           "Schedule", "Structure", "field_docs", "preset"]
