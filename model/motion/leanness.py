"""What a scene does not need, decided from its data and recorded in the checkpoint.

- colour channels: what the anchor frames have (a DAVIS346's APS frames: 1, grey) — ``from_arrays``;
- SH degree: a camera that never changes its direction to the scene cannot observe view dependence,
  so its Gaussians get degree 0 whatever the configured maximum (``choose_sh_degree``);
- a static camera: its trajectory is stored as one pose (no interpolation at inference);
- a recording without events: no event branch (``events_decision``), and a server without a sensor;
- frozen control points: those whose prior motion over the whole span moves none of their Gaussians
  by more than a threshold; Gaussians bound only to frozen points keep their canonical pose at
  inference (``frozen_control_points``), an error of at most the threshold (world units) per mean.
  ``EdMCGS.deform`` checks the frozen points' motion at each query (prior and events, ``motion_bound``)
  and skins every Gaussian where it is beyond: the bound holds at every time, not only at the samples.

``decisions`` gathers these as the checkpoint's ``meta["lean"]`` (plain JSON-able values).
"""

from __future__ import annotations

import math

import numpy as np
import torch

SH_STATIC_DEG = 2.0
"""Below this spread of viewing directions (degrees) the views cannot tell view-dependent colour from
noise: degree 0."""
SH_NARROW_DEG = 20.0
"""Below this spread, degree 1 at most (a low-order lobe is all a narrow arc constrains)."""
FREEZE_FRACTION = 1e-3
"""Default freeze threshold as a fraction of the scene extent: about 0.2 px on a DAVIS346 view of the
whole scene."""
FREEZE_SAMPLES = 128
"""Times sampled over the span to bound each control point's motion."""


def view_spread_deg(c2w: np.ndarray, center: np.ndarray) -> float:
    """Largest angle (degrees) between two of the cameras' directions to the scene centre.

    c2w: np.ndarray     # [T, 4, 4] float64 camera-to-world poses (trajectory samples and anchors)
    center: np.ndarray  # [3] float64 scene centre
    """
    rays = np.asarray(center, dtype=np.float64)[None] - np.asarray(c2w, dtype=np.float64)[:, :3, 3]
    norm = np.linalg.norm(rays, axis=1, keepdims=True)
    rays = rays[norm[:, 0] > 1e-12] / norm[norm[:, 0] > 1e-12]
    if len(rays) < 2:
        return 0.0
    rays = rays[np.linspace(0, len(rays) - 1, min(len(rays), 512)).round().astype(int)]  # all pairs
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0))))


def choose_sh_degree(c2w: np.ndarray, center: np.ndarray, max_degree: int) -> tuple[int, dict]:
    """(degree, record): the SH degree the cameras can constrain, at most ``max_degree``."""
    spread = view_spread_deg(c2w, center)
    if spread < SH_STATIC_DEG:
        degree, why = 0, f"the views span {spread:.2f} deg (< {SH_STATIC_DEG:g}): no view dependence seen"
    elif spread < SH_NARROW_DEG:
        degree = min(1, max_degree)
        why = f"the views span {spread:.1f} deg (< {SH_NARROW_DEG:g}): degree 1 at most"
    else:
        degree, why = max_degree, f"the views span {spread:.1f} deg: the configured maximum"
    return degree, {"value": int(degree), "max": int(max_degree), "view_spread_deg": round(spread, 3),
                    "why": why}


def events_decision(num_events: int, events: bool) -> tuple[bool, str | None]:
    """(events switch, message): a recording without events trains no event branch."""
    if num_events == 0 and events:
        return False, "the recording has no events: training without the event branch (events=false)"
    return events, None


@torch.no_grad()
def control_reach(model) -> torch.Tensor:
    """[M] float32: per control point, the distance to the farthest Gaussian bound to it (world units),
    the lever arm its rotation moves that Gaussian by."""
    cp = model.control
    return bound_reach(model.gaussians.means.detach(), cp.positions, cp.bind)


def bound_reach(means: torch.Tensor, positions: torch.Tensor, bind: torch.Tensor) -> torch.Tensor:
    """[M] ``control_reach`` of Gaussians ``means`` [N, 3] bound by ``bind`` [N, K] to ``positions`` [M, 3]
    (0 for a point no Gaussian is bound to)."""
    dist = (means[:, None, :] - positions[bind]).norm(dim=-1)                   # [N, K]
    return torch.zeros(positions.shape[0], device=means.device).scatter_reduce(
        0, bind.reshape(-1), dist.reshape(-1), reduce="amax")


def motion_bound(trans: torch.Tensor, rot: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """[M] the most each control point's rigid transform moves any of its Gaussians: |T_k| + theta_k r_k.

    |(R - I) v| = 2 sin(theta / 2) |v| <= theta |v|, and LBS is a convex blend, so a Gaussian whose K
    points all bound below epsilon moves by less than epsilon.
    trans: [M, 3], rot: [M, 4] unit quaternions, reach: [M] (``control_reach``)
    """
    theta = 2.0 * torch.acos(rot[:, 0].abs().clamp(max=1.0))
    return trans.norm(dim=-1) + theta * reach


@torch.no_grad()
def control_motion_bound(model, samples: int = FREEZE_SAMPLES) -> torch.Tensor:
    """[M] float32: per control point, the most its prior motion moves any of its Gaussians, sampled
    at ``samples`` times over the span (world units; ``motion_bound``).

    With anchor windows a point only draws in its own window, moved relative to that window's anchor:
    it is sampled there (``samples`` times per window), as ``deform`` moves it.
    """
    cp = model.control
    reach = control_reach(model)
    bound = torch.zeros(cp.num_points, device=reach.device)
    if cp.birth is None:
        for t in np.linspace(0.0, 1.0, samples):
            trans, rot, _ = model.control_motion(float(t))
            bound = torch.maximum(bound, motion_bound(trans, rot, reach))
        return bound
    meta = model.meta
    starts = [meta.normalized_time(int(a)) for a in meta.anchors_us]
    ends = [*starts[1:], 1.0]
    for w, (since, end) in enumerate(zip(starts, ends, strict=True)):
        rows = model.window_rows(w)
        if rows.own == 0:
            continue
        mine = rows.control[:rows.own]  # the window's own points, moved only there: one window's work
        for t in np.linspace(since, end, samples):
            trans, rot, _ = model.control_motion(float(t), window=w)
            moved = motion_bound(trans[:rows.own], rot[:rows.own], reach[mine])
            bound[mine] = torch.maximum(bound[mine], moved)
    return bound


def frozen_control_points(model, threshold: float | None = None,
                          samples: int = FREEZE_SAMPLES) -> tuple[np.ndarray, float]:
    """(mask [M] bool, threshold): control points whose motion bound stays below ``threshold`` (world
    units; default ``FREEZE_FRACTION`` of the scene extent) over the whole span."""
    if threshold is None:
        threshold = FREEZE_FRACTION * float(model.extent)
    if not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be a finite number >= 0, got {threshold}")
    bound = control_motion_bound(model, samples)
    return (bound <= threshold).cpu().numpy(), float(threshold)


def decisions(model, frozen: np.ndarray | None, threshold: float, static_camera: bool) -> dict:
    """The checkpoint's ``meta["lean"]``: what the scene leaves out, with the numbers behind it."""
    meta = model.meta
    lean = dict(meta.lean or {})
    lean["channels"] = {"value": int(meta.channels),
                        "why": "grey anchor frames" if meta.channels == 1 else "colour anchor frames"}
    lean["event_branch"] = {"value": bool(meta.has_event_branch),
                            "why": "configured" if meta.has_event_branch else
                            "no events in the recording or the config's switches"}
    lean["static_camera"] = {"value": bool(static_camera),
                             "why": "every trajectory pose equal: stored as one" if static_camera
                             else "the camera moves"}
    if frozen is not None:
        bind = model.control.bind.cpu().numpy()
        still = np.asarray(frozen)[bind].all(-1)
        lean["frozen"] = {"control_points": int(np.count_nonzero(frozen)), "of": len(frozen),
                          "gaussians_still": int(np.count_nonzero(still)), "gaussians": len(still),
                          "threshold": float(threshold), "samples": FREEZE_SAMPLES}
    return lean
