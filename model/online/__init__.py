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
past the span (g_phi, the checkpoint's distilled one of ``distill``, or none) the server
chooses by how well each predicted the recent frames (``prediction_losses``); ``finetune`` (off by
default) lets a copy of it learn from the corrections.

Modules: ``transition`` (an anchor's motion moved by the events, its Gaussians), ``correct`` (the fit
against a frame), ``distill`` (the transition learnt from the checkpoint's own motion), ``bounds`` (what
the events since a frame say of each pixel: their integration, and a render projected into its bounds).
The first two are this package's API; the others are imported by name.
"""

from edmcgs.model.online.correct import correct, finetune, fit_target, prediction_losses, spawn
from edmcgs.model.online.transition import (
    Motion,
    advance,
    checkpoint_motion,
    event_displacement,
    last_window,
    motion_codes,
    recolored,
    state_of,
    with_spawned,
)

__all__ = ["Motion", "advance", "checkpoint_motion", "correct", "event_displacement", "finetune",
           "fit_target", "last_window", "motion_codes", "prediction_losses", "recolored", "spawn", "state_of",
           "with_spawned"]
