"""Evaluation at held-out times through the inference API (the same path the server renders with)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.model.data import TrainingData
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.eval.lpips import LPIPS
from edmcgs.model.eval.metrics import psnr, ssim_score


@dataclass
class FrameScore:
    """The scores of one held-out frame."""

    index: int
    """Index into the recording's held-out frames."""
    t_us: int
    """Its time (absolute microseconds)."""
    anchor_us: int
    """tau(t): the anchor its state is propagated from."""
    events: int
    """Sum of |I_E| over [tau(t), t): how many events drove the transition (a lower bound)."""
    psnr: float
    ssim: float
    """SSIM over windows inside the image (``ssim.py``'s "valid" convention)."""
    lpips: float | None = None
    """LPIPS-VGG, when the evaluation was given its weights."""
    ssim_3dgs: float | None = None
    """SSIM in the 3DGS papers' convention (zero-padded, borders included): the one to set beside theirs."""


def render_held_out(model: EdMCGS, data: TrainingData, i: int, *, fast: bool = True,
                    own_poses: bool = False) -> tuple[np.ndarray, int, int]:
    """(image [H, W, C] float32 in [0, 1], tau(t), events) of held-out frame ``i``: the state at its time
    driven by the events since tau(t), rendered from its camera. own_poses: that camera as the model's
    trajectory has it (poses the model estimated, in its own world frame), not as ``data`` has it."""
    t = int(data.held_out_t_us[i])
    tau = model.tau(t)
    emap = None
    if data.event_map is not None and t > tau:
        emap = np.asarray(data.event_map(tau, t), dtype=np.float32)
    camera = model.meta.trajectory.at(t) if own_poses else None
    state = model.deform(t, emap, data.trajectory.at(t) if camera is None else camera)
    image = model.render(state, data.held_out_pose(i) if camera is None else camera, model.meta.intrinsics,
                         fast=fast)
    return image, tau, 0 if emap is None else int(np.abs(emap).sum())


def evaluate(model: EdMCGS, data: TrainingData, indices: np.ndarray | None = None, *,
             fast: bool = True, lpips: LPIPS | None = None) -> list[FrameScore]:
    """Render every held-out frame in ``indices`` (default: all evaluable ones) and score it
    (LPIPS too when ``lpips`` is given)."""
    indices = data.evaluable() if indices is None else np.asarray(indices)
    rows = []
    for i in indices.tolist():
        image, tau, events = render_held_out(model, data, i, fast=fast)
        target = data.held_out_images[i].astype(np.float32) / 255.0
        score = None if lpips is None else lpips.score(image, target)
        rows.append(FrameScore(i, int(data.held_out_t_us[i]), tau, events, psnr(image, target),
                               ssim_score(image, target), score, ssim_score(image, target, "3dgs")))
    return rows


def summarize(rows: list[FrameScore]) -> dict[str, float]:
    """Mean PSNR / SSIM (both conventions) and LPIPS when scored, over frames (NaN when there are none)."""
    if not rows:
        return {"psnr": float("nan"), "ssim": float("nan"), "frames": 0}
    out = {"psnr": float(np.mean([r.psnr for r in rows])), "ssim": float(np.mean([r.ssim for r in rows])),
           "frames": len(rows)}
    if all(r.ssim_3dgs is not None for r in rows):
        out["ssim_3dgs"] = float(np.mean([r.ssim_3dgs for r in rows]))
    if rows[0].lpips is not None:
        out["lpips"] = float(np.mean([r.lpips for r in rows]))
    return out
