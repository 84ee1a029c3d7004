"""Training of EdMCGS: composes the losses, schedules and density control of their own modules.

A run takes ``config.total_steps`` steps (a fixed number, or a number per span between anchors). With
anchor windows a step works on the windows it draws alone (their Gaussians and control points, the
event sums of their gap: ``EventGrid`` makes them on demand), so its cost does not grow with the
recording's length; the optimizer steps the rows of the windows drawn alone (``RowAdam``, lazy: a
window's momentum moves are paid when it is drawn again). Data-parallel: each worker draws
from its ``shard`` of the windows and ``sync`` averages the gradients (``sync.GradientSync``).

One iteration:
  * an anchor frame: the state at tau_n with an empty window, photometric loss (L1 + D-SSIM);
  * with events: a gap n and two sub-step times t_a < t_b in it (t_a may be the anchor, t_b the next
    anchor), each state driven by the events since tau_n; the event loss compares the rendered
    log-luminance change (colours detached) with C * sum(p) over [t_a, t_b); TLI on the control
    points between t_a and t_b; Laplacian smoothness of g_phi's displacement;
  * without events: TLI between two nearby times.

With a static set (config.static_set), at ``lift_at`` the anchor pixels its render does not explain
are lifted into their anchors' windows (``lift_movers``): from then on the windows hold what moves.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.profiler import record_function as stage  # a named range when profiled (bench.train_step)
from tqdm.auto import tqdm

from edmcgs.atomic import atomic_output
from edmcgs.errors import InvalidInputError, TrainingError
from edmcgs.geometry import Intrinsics, world_to_camera
from edmcgs.model.checkpoint import save_checkpoint
from edmcgs.model.data import EventGrid, TrainingData
from edmcgs.model.dynamic import EdMCGS, background_color, render_image
from edmcgs.model.eval.evaluation import evaluate, summarize
from edmcgs.model.motion.gaussians import PER_GAUSSIAN, STATIC, Gaussians, GaussianState
from edmcgs.model.motion.initialization import backproject_anchors
from edmcgs.model.motion.skinning import lbs
from edmcgs.model.motion.windows import WindowRows, with_static
from edmcgs.model.render.projection import NEAR, may_draw
from edmcgs.model.train.curves import Curves
from edmcgs.model.train.density import (
    GradientStats,
    append,
    densify_and_prune,
    reset_opacity,
    screen_space_grad,
)
from edmcgs.model.train.losses import event_loss, laplacian_smoothness, photometric_loss, pyramid_l1, tli_loss
from edmcgs.model.train.resume import remove_sidecar, save_final
from edmcgs.model.train.row_adam import RowAdam
from edmcgs.model.train.schedule import exp_decay, ramp
from edmcgs.model.train.sync import GradientSync

MAX_BAD_STEPS = 20
"""Consecutive non-finite losses after which training stops with a TrainingError."""


def _resize(images: Tensor, height: int, width: int) -> Tensor:
    """[B, H, W, C] -> [B, height, width, C] by area averaging (identity at the same size)."""
    if images.shape[1:3] == (height, width):
        return images
    return F.interpolate(images.permute(0, 3, 1, 2), size=(height, width), mode="area").permute(0, 2, 3, 1)


class Trainer:
    """Optimises a model on one recording's arrays; ``fit`` runs to ``total_steps``.

    sync: a data-parallel run's exchange (``sync.GradientSync``): this worker draws its samples from its
    shard of the windows, takes ``1 / world`` of the steps (each counting ``world`` samples: ``step``
    advances by ``world``), and only rank 0 evaluates and writes checkpoints.
    """

    def __init__(self, model: EdMCGS, data: TrainingData, *, device: str | torch.device = "cpu",
                 progress: bool = True, clock: Callable[[], float] = time.perf_counter,
                 compile: bool = False, sync: GradientSync | None = None):
        """compile: the step's pure tensor functions (skinning, the prior's network, the event branch, the
        image losses) by ``torch.compile``: after a compile of about a minute on the first steps, a CPU
        step takes about 0.7 of the time (on a GPU the gain is not established: docs/benchmarks/gpu.md);
        the values agree with the default to float32 rounding, not bit for bit."""
        self.cfg = cfg = model.config
        self.sync = sync
        rank, world = (0, 1) if sync is None else (sync.rank, sync.world)
        self.lead = rank == 0
        """Whether this process evaluates and writes checkpoints (rank 0 of a data-parallel run)."""
        self.stride = world
        """Samples per step (the workers'): ``step`` counts samples, so schedules read the same."""
        self.total_steps = cfg.total_steps(len(data.anchors_t_us))
        """Samples of the whole run (``config.total_steps``)."""
        self.clock = clock
        """Seconds for ``train_seconds`` (a test passes its own)."""
        if cfg.events and data.event_map is None:
            raise TrainingError("config.events is on but the recording gives no event source")
        if data.channels != model.meta.channels:
            raise InvalidInputError(f"the data has {data.channels} channels, the model {model.meta.channels}")
        self.device = torch.device(device)
        self.model = model.to(self.device).train()
        self.photometric_loss, self.pyramid_l1, self.event_loss = photometric_loss, pyramid_l1, event_loss
        if compile:
            # Fused kernels, forward and backward: a few each instead of hundreds of small ops. The point
            # counts change with the windows (dynamic shapes), the image sizes do not (one graph each).
            self.model.skinning = torch.compile(lbs, dynamic=True)
            self.model.prior.compiled_field = torch.compile(self.model.prior.field, dynamic=True)
            if self.model.transition is not None:
                self.model.compiled_event_motion = torch.compile(self.model.event_motion, dynamic=True)
            self.photometric_loss, self.pyramid_l1, self.event_loss = (
                torch.compile(f, dynamic=False) for f in (photometric_loss, pyramid_l1, event_loss))
        self.extent = float(model.extent)
        """The scene's extent (a constant buffer), read once: the schedules need it every step."""
        self.data = data
        self.progress = progress and self.lead
        intr = model.meta.intrinsics
        w, h = max(8, round(intr.width * cfg.train_scale)), max(8, round(intr.height * cfg.train_scale))
        self.intr = intr if (w, h) == (intr.width, intr.height) else intr.scaled(w, h)
        ew, eh = max(8, round(w * cfg.event_render_scale)), max(8, round(h * cfg.event_render_scale))
        self.event_intr = self.intr if (ew, eh) == (w, h) else self.intr.scaled(ew, eh)
        images = torch.from_numpy(data.anchor_images).float() / 255.0
        self.anchor_images = _resize(images, h, w).to(self.device)
        # Poses on the device (losses, projections) and the same float32 values on the host (the cameras
        # of renders): a render then reads nothing back from the device to check its camera.
        self.anchor_w2c = self._w2c(data.anchor_poses)
        self.anchor_w2c_host = self.anchor_w2c.cpu().numpy()
        self.anchor_times = [model.meta.normalized_time(int(t)) for t in data.anchors_t_us]
        self.anchor_shard = np.array_split(np.arange(len(self.anchor_times)), world)[rank]
        """The anchors this worker draws (all but in a data-parallel run)."""
        self.grid = EventGrid.build(data, cfg.substeps, device=self.device) if cfg.events else None
        self.gap_shard = None
        if self.grid is not None:
            self.gap_shard = np.array_split(np.arange(self.grid.num_gaps), world)[rank]
            if len(self.anchor_shard) == 0 or len(self.gap_shard) == 0:
                raise InvalidInputError(f"{world} workers for {len(self.anchor_times)} anchors: each needs "
                                        "at least one window")
            g, s1 = self.grid.times.shape
            self.grid_w2c = self._w2c(data.trajectory.at(self.grid.times.reshape(-1))).reshape(g, s1, 4, 4)
            self.grid_w2c_host = self.grid_w2c.cpu().numpy()
            self.grid_t = [[model.meta.normalized_time(int(t)) for t in row] for row in self.grid.times]
        self.background = background_color(cfg, model.meta.channels).to(self.device)
        self.optimizer = self._build_optimizer()
        self.stats = GradientStats(len(model.gaussians), self.device)
        self.step = 0
        self.bad_steps = 0
        if sync is not None:
            sync.broadcast(self.model)  # one model everywhere, whatever each worker's initialisation
        self.rng = np.random.default_rng(cfg.seed if rank == 0 else [cfg.seed, rank])
        self.generator = torch.Generator(device=self.device).manual_seed(cfg.seed)
        self.history: list[dict] = []
        self.train_seconds = 0.0
        """Wall-clock seconds spent in training steps (not in evaluation or checkpointing)."""
        self.interrupted = False
        """Whether the last ``fit`` stopped early at its ``stop`` event."""
        self.saved_step: int | None = None
        """The step of the last checkpoint ``fit`` wrote (None: none yet)."""
        birth = model.gaussians.birth
        self.lifted = not cfg.static_set or (birth is not None and bool((birth >= 0).any()))
        """Whether what moves has been lifted into the anchor windows (config.static_set: at lift_at; a
        trained model's windows already hold it)."""
        self.lift_counts: list[int] = []
        """Gaussians lifted into each anchor's window (config.static_set), once lifted."""
        self.grown_at: int | None = None
        """The step that last added Gaussians (densified or lifted); until trained, they draw worse."""

    def reschedule(self, iterations: int) -> None:
        """The run's schedule set to ``iterations`` steps (fixed, not per window), training going on from
        this step: the schedules read the new length from the next step, as ``edmcgs train --resume --set
        iterations=N`` does."""
        model = self.model
        model.config = self.cfg = self.cfg.replace(iterations=int(iterations), steps_per_window=0)
        model.meta.config = model.config.to_dict()
        self.total_steps = self.cfg.total_steps(len(self.data.anchors_t_us))

    # ------------------------------------------------------------------ setup
    def _w2c(self, c2w: np.ndarray) -> Tensor:
        return torch.as_tensor(world_to_camera(c2w), dtype=torch.float32, device=self.device)

    def _build_optimizer(self) -> torch.optim.Adam:
        m = self.model
        g = m.gaussians
        params = {"means": [g.means], "quats": [g.quats], "log_scales": [g.log_scales],
                  "opacity_logits": [g.opacity_logits], "features": [g.features],
                  "radius": [m.control.log_radius], "deform": list(m.prior.parameters())}
        if m.bg_layer is not None:
            params["background"] = [m.bg_layer.texture]
        if m.transition is not None:
            params["event"] = [*m.encoder.parameters(), *m.transition.parameters()]
        # With anchor windows a step moves only the Gaussians of the windows it drew; on CUDA one fused
        # kernel per step for the other groups instead of several per parameter group.
        rows = PER_GAUSSIAN if model_has_windows(m) else ()
        # Data parallel: a step averages `world` samples, so a parameter every sample moves takes 1/world
        # of the updates; Adam's square-root rule keeps its path (a window's rows are drawn as often as in
        # one process and keep their rate). 3 s of traffic, 2 workers: -0.48 dB against one without it,
        # -0.09 dB with it.
        self.lr_scale = {name: 1.0 if name in rows else math.sqrt(self.stride) for name in params}
        lrs = self._learning_rates(0.0)
        groups = [{"name": name, "params": p, "lr": lrs[name]} for name, p in params.items()]
        return RowAdam(groups, row_groups=rows, eps=1e-15, fused=True if self.device.type == "cuda" else None)

    def _learning_rates(self, progress: float) -> dict[str, float]:
        """Each parameter group's learning rate at ``progress`` (data-parallel scale included)."""
        cfg = self.cfg
        lrs = {"means": exp_decay(cfg.lr_means * self.extent, 0.01, progress), "quats": cfg.lr_quats,
               "log_scales": cfg.lr_scales, "opacity_logits": cfg.lr_opacity, "features": cfg.lr_features,
               "radius": cfg.lr_radius, "deform": exp_decay(cfg.lr_deform, 0.02, progress),
               "background": cfg.lr_background,
               "event": exp_decay(cfg.lr_event, 0.1, progress) * ramp(progress, *cfg.event_warmup)}
        return {name: lr * self.lr_scale[name] for name, lr in lrs.items() if name in self.lr_scale}

    def _set_schedules(self, progress: float) -> None:
        # every group, every step: a run resumed on another number of workers takes its own rates
        lrs = self._learning_rates(progress)
        for group in self.optimizer.param_groups:
            group["lr"] = lrs[group["name"]]
        # The event branch warms in by its learning rate, its output unscaled: its last layer starts at
        # zero, so it moves nothing until trained. An output scale ramped from 0 instead let Adam, whose
        # steps do not shrink with the gradient, grow the raw output while the scale was small, and the
        # ramp then multiplied it (30 s of traffic: control points thrown 2 scene extents, out of every
        # view and so out of every gradient, for the rest of training).
        if self.model.transition is not None:
            self.model.event_scale.fill_(1.0 if progress >= self.cfg.event_warmup[0] else 0.0)

    # ------------------------------------------------------------------ one step
    def _render(self, state: GaussianState, w2c: np.ndarray, intr=None, *,
                detach_layer: bool = False) -> Tensor:
        """w2c: the camera as a host array (``*_w2c_host``)."""
        intr = intr or self.intr
        layer = None
        if self.model.bg_layer is not None:
            layer = self.model.bg_layer.image(w2c[:3, :3].T, intr)
            layer = layer.detach() if detach_layer else layer
        return render_image(state, w2c, intr, self.background, layer)

    def _gap_motion(self, gap: int, k: int, cum: Tensor):
        """Control-point motion at grid time (gap, k), ``cum`` the gap's running event sums: the next
        anchor's state at the gap's end (with anchor windows: the gap's own control points, moved by all
        of its events)."""
        grid, model = self.grid, self.model
        emap = cum[k] if k > 0 else None
        windows = model_has_windows(model)
        if k == grid.substeps and grid.ends_at_anchor[gap] and not windows:
            return model.control_motion(self.anchor_times[gap + 1])
        return model.control_motion(self.grid_t[gap][k], emap, self.grid_w2c[gap, k],
                                    window=gap if windows else None, nonzero=bool(grid.nonzero(gap)[k]))

    def _draw(self, shard: np.ndarray) -> int:
        return int(shard[int(self.rng.integers(len(shard)))])

    def _graph(self, window: int | None) -> tuple[Tensor, Tensor]:
        """(control-point positions, their graph) the regularisers of a step read: with anchor windows
        those of ``window`` (its own points' edges), else every point's."""
        cp = self.model.control
        if window is None:
            return cp.positions, cp.graph
        rows = self.model.window_rows(window)
        return cp.positions[rows.control], rows.graph

    def _rows_in_view(self, cameras: dict[int, list[tuple[Tensor, Intrinsics]]]) -> dict[int, WindowRows]:
        """Per window, ``window_rows(window)`` drawing, of the static set, only what its ``cameras`` (w2c,
        intrinsics) can see: the rest has no gradient, and a long moving-camera recording's static set is
        mostly out of any one view. Exact: the bound (``may_draw``) lets each row move as far as the
        momentum it owes (``RowAdam.reach``) would take it before the step reads it."""
        g, opt = self.model.gaussians, self.optimizer
        static = torch.nonzero(g.birth == STATIC)[:, 0]
        if len(static) == 0:
            return {w: self.model.window_rows(w) for w in cameras}
        means = g.means.detach()[static]
        scales = g.log_scales.detach()[static].amax(-1).exp()
        reach, growth = math.sqrt(3) * opt.reach(g.means), math.exp(opt.reach(g.log_scales))
        out = {}
        for window, cams in cameras.items():
            seen = torch.zeros(len(static), dtype=torch.bool, device=static.device)
            for w2c, intr in cams:
                seen |= may_draw(means, scales, w2c, intr, NEAR, reach=reach, growth=growth)
            out[window] = with_static(self.model.window_rows(window), g.birth, static[seen])
        return out

    def train_step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms (floats).

        On a GPU the step reads the device back once, for the loss and its terms together (whether the
        loss is finite decides the step); everything else stays queued on the device."""
        cfg, model = self.cfg, self.model
        # Past the run's steps (``fit(until=...)`` beyond them) every schedule stays at its end.
        progress = min(self.step / self.total_steps, 1.0)
        self._set_schedules(progress)
        if not self.lifted and progress >= cfg.lift_at:
            with stage("lift movers"):
                self.lift_movers()
        static = progress < cfg.deform_from
        terms: dict[str, Tensor] = {}

        n = self._draw(self.anchor_shard)
        paired = not static and self.grid is not None  # an event pair in a gap besides the anchor
        if paired:
            gap = self._draw(self.gap_shard)
            s = self.grid.substeps
            a = 0 if self.rng.random() < cfg.anchored_pairs else int(self.rng.integers(0, s))
            b = int(self.rng.integers(a + 1, min(s, a + cfg.max_pair_steps) + 1))
        # With anchor windows a step's work is the rows of the windows it draws (and the static set)
        rowwise = model_has_windows(model)
        rows = in_view = None
        if rowwise:
            cameras = {n: [(self.anchor_w2c[n], self.intr)]}
            if paired:
                cameras.setdefault(gap, []).extend([(self.grid_w2c[gap, a], self.event_intr),
                                                    (self.grid_w2c[gap, b], self.event_intr)])
                if gap + 1 < len(self.anchor_w2c):  # the next anchor's frame
                    cameras[gap].append((self.anchor_w2c[gap + 1], self.intr))
            with stage("rows in view"):
                in_view = self._rows_in_view(cameras)
                rows = torch.unique(torch.cat([r.drawn for r in in_view.values()]))
            with stage("optimizer: catch-up"):
                self.optimizer.catch_up(rows)  # their momentum moves since last drawn, before they are read
        with stage("anchor: deform"):
            weights = None
            if rowwise:
                anchor_state = model.state_at(self.anchor_times[n], static=static, window=n, rows=in_view[n])
            else:
                weights = model.control.weights(model.gaussians.means)  # the same for every skin of this step
                anchor_state = model.state_at(self.anchor_times[n], static=static, weights=weights)
            anchor_state.means.retain_grad()
        with stage("anchor: render"):
            image = self._render(anchor_state, self.anchor_w2c_host[n])
        with stage("anchor: photometric loss"):
            terms["photo"] = self.photometric_loss(image, self.anchor_images[n], cfg.lambda_dssim)
        loss = terms["photo"]

        if paired:
            with stage("event pair: sums"):
                cum = self.grid.cumulative(gap)
            with stage("event pair: control motion"):
                trans_a, rot_a, disp_a = self._gap_motion(gap, a, cum)
                trans_b, rot_b, disp_b = self._gap_motion(gap, b, cum)
            renders = []
            for trans, rot, k in ((trans_a, rot_a, a), (trans_b, rot_b, b)):
                with stage("event pair: skin"):
                    st = model.window_state(trans, rot, gap, rows=in_view[gap]) if rowwise else \
                        model.state_from_motion(trans, rot, weights=weights)
                    st = GaussianState(st.means, st.quats, st.scales, st.opacities, st.colors.detach())
                with stage("event pair: render"):
                    renders.append(self._render(st, self.grid_w2c_host[gap, k], self.event_intr,
                                                detach_layer=True))
            with stage("event pair: event loss"):
                events = cum[b] - cum[a]
                ei = self.event_intr
                events = _resize(events[None, :, :, None], ei.height, ei.width)[0, :, :, 0]
                terms["event"] = self.event_loss(renders[0], renders[1], events, cfg.contrast_threshold,
                                            cfg.log_eps, levels=cfg.event_loss_levels)
            loss = loss + cfg.lambda_event * terms["event"]
            cp, graph = self._graph(gap if rowwise else None)
            if cfg.tli:
                terms["tli"] = tli_loss(cp + trans_a, cp + trans_b, graph)
                loss = loss + cfg.lambda_tli * terms["tli"]
            if rowwise and cfg.lambda_next > 0 and self.grid.ends_at_anchor[gap] and self.lifted:
                # The gap's Gaussians carried by all its events to the next anchor frame.
                with stage("next anchor"):
                    trans_e, rot_e, _ = (trans_b, rot_b, None) if b == s else self._gap_motion(gap, s, cum)
                    st = model.window_state(trans_e, rot_e, gap, motion_only=True, rows=in_view[gap])
                    image_next = self._render(st, self.anchor_w2c_host[gap + 1])
                    target = self.anchor_images[gap + 1]
                    terms["next"] = self.photometric_loss(image_next, target, cfg.lambda_dssim) \
                        + self.pyramid_l1(image_next, target, cfg.next_levels)
                loss = loss + cfg.lambda_next * terms["next"]
            disps = [d for d in (disp_a, disp_b) if d is not None]
            if disps:
                terms["edisp"] = torch.stack([d.detach().norm(dim=-1).mean() for d in disps]).mean() \
                    / model.extent
                terms["dead"] = model.encoder.dead
                terms["smooth"] = sum(laplacian_smoothness(d, graph) for d in disps) / len(disps)
                loss = loss + cfg.lambda_smooth * terms["smooth"]
        elif not static and cfg.tli:
            # Time-only model: isometry between two nearby times, dt one sub-step of an average gap.
            dt = 1.0 / (max(len(self.anchor_times) - 1, 1) * cfg.substeps)
            t = float(self.rng.uniform(dt / 2, 1 - dt / 2))
            window = n if rowwise else None  # with anchor windows: the drawn anchor's points
            trans_1, _, _ = model.control_motion(t - dt / 2, window=window)
            trans_2, _, _ = model.control_motion(t + dt / 2, window=window)
            cp, graph = self._graph(window)
            terms["tli"] = tli_loss(cp + trans_1, cp + trans_2, graph)
            loss = loss + cfg.lambda_tli * terms["tli"]

        self.optimizer.zero_grad(set_to_none=True)
        values = torch.stack([loss.detach(), *(v.detach().float() for v in terms.values())]).tolist()
        finite = math.isfinite(values[0])
        if self.sync is not None:  # every worker skips the step when one has a non-finite loss
            flag = torch.tensor([0.0 if finite else 1.0])
            self.sync.sum_(flag)
            finite = float(flag) == 0.0
        if not finite:
            self.bad_steps += 1
            if self.bad_steps > MAX_BAD_STEPS:
                raise TrainingError(f"the loss was not finite for {self.bad_steps} steps in a row "
                                    f"(step {self.step})")
            self.step += self.stride
            return {"loss": float("nan")}
        with stage("backward"):
            loss.backward()
        if self.sync is not None:
            with stage("all-reduce"):
                if rows is not None:  # the other workers' rows too: current before the step
                    rows = self.sync.union(rows)
                    self.optimizer.catch_up(rows)
                self.sync.average(self.optimizer, self.optimizer.row_groups, rows)
        self.optimizer.rows = rows
        self._sanitize_gradients()
        self.bad_steps = 0
        if cfg.densify_from <= progress < cfg.densify_until and anchor_state.means.grad is not None:
            self.stats.add(screen_space_grad(anchor_state.means.grad, anchor_state.means.detach(),
                                             self.anchor_w2c[n], self.intr.fx, self.intr.fy,
                                             self.intr.width, self.intr.height),
                           in_view[n].drawn if rowwise else None)
        with stage("optimizer step"):
            self.optimizer.step()
        self.step += self.stride
        with stage("density control"):
            self._density_control(progress)
        out = dict(zip(terms, values[1:], strict=True))
        out["loss"] = values[0]
        return out

    @torch.no_grad()
    def lift_movers(self) -> None:
        """Lift every anchor's pixels that the static set's render (with the background layer) misses by
        more than ``dynamic_threshold`` into the anchor's window, at the render's depth where it has
        one (``backproject_anchors``); then sample the control points from them."""
        cfg, model, data = self.cfg, self.model, self.data
        self.settle()  # renders the model whole, then adds rows
        intr = model.meta.intrinsics
        was_training = model.training
        model.eval()
        try:
            misses, depths = [], []
            for n, pose in enumerate(data.anchor_poses):
                state = model.state_at(self.anchor_times[n], window=n)
                image = model.render(state, pose, intr, fast=False)
                depth, alpha = model.render_depth_alpha(state, pose, intr, fast=False)
                target = data.anchor_images[n].astype(np.float32) / 255.0
                misses.append(np.abs(image - target).max(-1) > cfg.dynamic_threshold)
                depths.append(np.where(alpha > 0.5, depth, 0.0))
        finally:
            model.train(was_training)
        misses = np.stack(misses)
        self.lifted = True
        self.grown_at = self.step
        self.lift_counts = [0] * len(misses)
        if not misses.any():
            return
        rng = np.random.default_rng(cfg.seed + 1)
        points, colors, scales, views = backproject_anchors(
            data.anchor_images, data.anchor_poses, intr, model.center.cpu().numpy().astype(np.float64),
            float(model.extent), cfg.initial_points(len(misses)), rng, np.zeros(data.channels),
            candidates=misses, depth=np.stack(depths), return_views=True)
        self.lift_counts = np.bincount(views.numpy(), minlength=len(misses)).tolist()
        g = model.gaussians
        new = Gaussians.from_points(points, colors, scales, sh_degree=g.sh_degree, opacity=cfg.init_opacity,
                                    birth=views)
        append(g, self.optimizer, {name: getattr(new, name).detach().to(self.device)
                                   for name in (*PER_GAUSSIAN, "birth")})
        model.control.resample(g.means, radius=cfg.radius_init * float(model.extent), birth=g.birth)
        self._forget("radius")
        self.stats = GradientStats(len(g), self.device)

    def _due(self, every: int) -> bool:
        """Whether the last step crossed a multiple of ``every`` (a step counts ``stride`` samples)."""
        return bool(every) and self.step // every != (self.step - self.stride) // every

    def _sanitize_gradients(self) -> None:
        # A single degenerate splat can produce a NaN gradient entry; zeroing it keeps Adam's moments finite.
        for group in self.optimizer.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.grad.is_sparse:  # a window's rows (motion.row_grad): their values alone
                    p.grad = p.grad.coalesce()
                torch.nan_to_num_(p.grad.values() if p.grad.is_sparse else p.grad, nan=0.0, posinf=0.0,
                                  neginf=0.0)

    def _density_control(self, progress: float) -> None:
        cfg, model = self.cfg, self.model
        if not (cfg.densify_from <= progress < cfg.densify_until):
            return
        if self._due(cfg.densify_every) or self._due(cfg.opacity_reset_every):
            self.settle()  # density control reads and edits every row
        if self._due(cfg.densify_every):
            if self.sync is not None:  # every worker's views: the same Gaussians added everywhere
                self.sync.sum_(self.stats.total, self.stats.count)
            extent, cap = self.extent, cfg.gaussian_cap(len(self.data.anchors_t_us))
            densify_and_prune(model.gaussians, self.optimizer, self.stats, grad_threshold=cfg.densify_grad,
                              extent=extent, percent_dense=cfg.percent_dense, min_opacity=cfg.prune_opacity,
                              max_size=cfg.prune_size * extent, max_count=cap,
                              generator=self.generator)
            self.stats = GradientStats(len(model.gaussians), self.device)
            self.grown_at = self.step
            if progress < cfg.control_resample_until and len(model.gaussians) >= model.control.num_points:
                model.control.resample(model.gaussians.means, radius=cfg.radius_init * extent,
                                       birth=model.gaussians.birth)
                self._forget("radius")
            else:
                model.control.rebind(model.gaussians.means, birth=model.gaussians.birth)
        if self._due(cfg.opacity_reset_every):
            reset_opacity(model.gaussians, self.optimizer)

    def _forget(self, name: str) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == name:
                for p in group["params"]:
                    self.optimizer.state.pop(p, None)

    # ------------------------------------------------------------------ loop, evaluation, resume
    def settle(self) -> None:
        """Bring every Gaussian current: the momentum moves the windows not drawn lately owe are paid
        (``RowAdam.flush``). Training does it before it reads the model whole (evaluation, density
        control, checkpoints); code that reads the model between steps calls it first."""
        self.optimizer.flush()

    def evaluate(self, frames: int | None = None) -> dict[str, float]:
        """Mean PSNR / SSIM on ``frames`` evenly spaced held-out frames (all when None)."""
        self.settle()
        idx = self.data.evaluable()
        if frames is not None and idx.size > frames:
            idx = idx[np.linspace(0, idx.size - 1, frames).round().astype(int)]
        was_training = self.model.training
        self.model.eval()
        try:
            # The PyTorch renderer: the numba one would reset torch's OpenMP thread count mid-training.
            return summarize(evaluate(self.model, self.data, idx, fast=False))
        finally:
            self.model.train(was_training)

    def fit(self, checkpoint_path: str | os.PathLike | None = None, *, until: int | None = None,
            stop: threading.Event | None = None, curves: Curves | None = None) -> list[dict]:
        """Train to step ``until`` (default ``total_steps``; past it the schedules stay at their end);
        periodic evaluation and resumable checkpoints. Returns the evaluation history ({step, psnr, ssim,
        frames, seconds, gaussians}); ``seconds`` counts training steps only (evaluations and checkpoints
        are off the clock).

        stop: when set (a Ctrl-C handler sets it), the current step is finished, a checkpoint with the
        optimizer state is written to ``checkpoint_path`` and ``fit`` returns with ``interrupted`` True.
        Otherwise the final checkpoint is written, and what resuming needs beside it (``resume``).
        curves: receives the scalars of every step and evaluation (``curves.Curves``).
        """
        cfg = self.cfg
        until = self.total_steps if until is None else int(until)
        self.interrupted = False
        bar = tqdm(total=until, initial=self.step, desc="train", disable=not self.progress,
                   dynamic_ncols=True)
        last: dict[str, float] = {}
        ema: dict[str, float] = {}
        while self.step < until:
            started = self.clock()
            lifted = self.lifted
            last = self.train_step()
            took = self.clock() - started
            if self.lifted and not lifted:
                bar.write(f"step {self.step}: {sum(self.lift_counts)} Gaussians lifted into the anchor "
                          "windows from the pixels the static set misses by more than "
                          f"{cfg.dynamic_threshold:g} (per anchor {min(self.lift_counts)} to "
                          f"{max(self.lift_counts)})")
            self.train_seconds += took
            for key, value in last.items():
                if math.isfinite(value):
                    ema[key] = value if key not in ema else 0.9 * ema[key] + 0.1 * value
            if curves is not None:
                curves.scalars(self.step, "train", {**last, "gaussians": len(self.model.gaussians),
                                                    "step_seconds": took})
            bar.update(min(self.stride, until - bar.n))
            if self._due(10) or self.step >= until:
                post = {k: f"{v:.4g}" for k, v in ema.items()}
                post["N"] = len(self.model.gaussians)
                bar.set_postfix(post, refresh=False)
            if self.lead and self._due(cfg.eval_every) and self.data.evaluable().size:
                result = {"step": self.step, **self.evaluate(cfg.eval_frames), "seconds": self.train_seconds,
                          "gaussians": len(self.model.gaussians), **{k: ema[k] for k in HEALTH if k in ema}}
                self.history.append(result)
                if curves is not None:
                    curves.scalars(self.step, "heldout", {k: result[k] for k in ("psnr", "ssim", "ssim_3dgs")
                                                          if k in result})
                bar.write(f"step {self.step}: held-out PSNR {result['psnr']:.2f} dB, "
                          f"SSIM {result['ssim']:.4f} "
                          f"({result['frames']} frames), {len(self.model.gaussians)} Gaussians"
                          + "".join(f", {k} {result[k]:.4g}" for k in HEALTH if k in result))
            if stop is not None and stop.is_set() and self.step < until:  # (not in a data-parallel run)
                self.interrupted = True
                break
            if checkpoint_path and self.lead and self._due(cfg.checkpoint_every) and self.step < until:
                self.save_resumable(checkpoint_path)
                if curves is not None:  # the curves on disk reach the checkpoint, whatever comes next
                    curves.flush()
        bar.close()
        if curves is not None:
            curves.flush()
        if self.interrupted:
            if checkpoint_path and self.lead:
                self.save_resumable(checkpoint_path)
            return self.history
        self.settle()
        if self.sync is not None and not self.sync.agree(self.model):
            raise TrainingError("the data-parallel workers' models differ at the end: nothing was written")
        self.model.event_scale.fill_(1.0)
        self.model.eval()
        if checkpoint_path and self.lead:
            save_final(self.model, checkpoint_path, self.train_state())
            self.saved_step = self.step
        return self.history

    def save_resumable(self, path: str | os.PathLike) -> None:
        """A mid-training checkpoint at ``path``: the model with the train state inside (a sidecar left
        by an earlier final checkpoint there is removed: it no longer belongs to the file)."""
        save_checkpoint(self.model, path, train_state=self.train_state())
        remove_sidecar(path)
        self.saved_step = self.step

    def train_state(self) -> dict:
        """Everything besides the model needed to continue this run (plain containers and tensors); the
        model is brought current first (``RowAdam.flush``), as a checkpoint of it follows."""
        self.settle()
        return {"step": self.step, "optimizer": self.optimizer.state_dict(), "stats": self.stats.state_dict(),
                "rng": self.rng.bit_generator.state, "generator": self.generator.get_state(),
                "history": self.history, "train_seconds": self.train_seconds, "lifted": self.lifted,
                "lift_counts": self.lift_counts}

    def load_train_state(self, state: dict) -> None:
        """Continue from ``train_state()`` output (the model must come from the same checkpoint)."""
        self.step = int(state["step"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.stats.load_state_dict(state["stats"])
        self.rng.bit_generator.state = state["rng"]
        self.generator.set_state(state["generator"])
        self.history = list(state.get("history", []))
        self.train_seconds = float(state.get("train_seconds", 0.0))
        self.lifted = bool(state.get("lifted", self.lifted))
        self.lift_counts = list(state.get("lift_counts", []))


def model_has_windows(model: EdMCGS) -> bool:
    """Whether the model's Gaussians live in anchor windows (config.anchor_windows)."""
    return model.gaussians.birth is not None


HEALTH = ("event", "edisp", "dead")
"""Training-health columns of the history: the event loss, the mean event displacement (scene extents)
and the fraction of Phi's second-layer channels never above 0 (moving averages at the evaluation)."""


def write_history_csv(history: list[dict], path: str | os.PathLike) -> None:
    """The evaluation history as CSV (step, psnr, ssim, frames, seconds, then the health columns,
    empty where a run has no event branch, then the Gaussian count)."""
    lines = ["step,psnr,ssim,frames,seconds," + ",".join(HEALTH) + ",gaussians"]
    lines += [f"{h['step']},{h['psnr']:.4f},{h['ssim']:.5f},{h['frames']},{h['seconds']:.1f},"
              + ",".join("" if h.get(k) is None else f"{h[k]:.5g}" for k in HEALTH)
              + f",{h.get('gaussians', '')}"
              for h in history]
    with atomic_output(path, TrainingError) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
