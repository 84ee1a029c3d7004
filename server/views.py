"""Where the checkpoint's cameras were: GET /scene's ``training_views``, for a client to tell a pose the
model was trained from (or near one) from an unseen view, where the scene smears."""

from __future__ import annotations

import numpy as np

MAX_VIEWS = 256
"""Most poses listed: evenly spaced over the trajectory, enough to cover a smooth camera path."""


def training_views(model) -> dict | None:
    """``{"center", "scale", "c2w"}``: the point the cameras look at (the model's scene centre), the
    median distance of the training cameras from it (the scene's scale: a view's displacement is
    measured against it), and the training poses (camera-to-world, 16 numbers row-major each: the
    event camera's trajectory over the span, the anchors' poses included). None: the checkpoint has
    no trajectory.
    """
    meta = model.meta
    traj = meta.trajectory
    if traj is None:
        return None
    t_us = np.asarray(traj.t_us, dtype=np.int64)
    c2w = np.asarray(traj.c2w, dtype=np.float64)
    inside = (t_us >= meta.t_start_us) & (t_us <= meta.t_end_us)
    if inside.any():
        c2w = c2w[inside]
    if len(c2w) > MAX_VIEWS:
        c2w = c2w[np.unique(np.linspace(0, len(c2w) - 1, MAX_VIEWS).round().astype(np.int64))]
    center = model.center.detach().cpu().numpy().astype(np.float64).reshape(3)
    scale = float(np.median(np.linalg.norm(c2w[:, :3, 3] - center, axis=1)))
    if not np.isfinite(scale) or scale <= 1e-9:  # cameras at the centre itself: the view's half-width there
        scale = float(model.extent)
    return {"center": center.tolist(), "scale": scale, "c2w": [m.reshape(-1).tolist() for m in c2w]}
