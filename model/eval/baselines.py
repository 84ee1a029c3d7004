"""The trivial baselines every score stands beside, on the same held-out frames: no model at all.

- **hold last anchor**: the newest anchor frame at or before t, shown as it is;
- **blend of neighbouring anchors**: the two anchors around t mixed linearly in time (after the last
  anchor, the last one held);
- **events integrated onto the last anchor**: the newest anchor frame moved forward by the events since
  it, pixel by pixel, with the sensor's own model: each event is a change of C in log intensity,
  log(I_t + eps) = log(I_tau + eps) + C E(p) (frame plus events, no model; C is the recording's contrast
  threshold when known, else ``DEFAULT_CONTRAST``; ``model/online/bounds.py``).

A method that does not beat them has not worked, whatever its absolute number.
"""

from __future__ import annotations

import numpy as np

from edmcgs.model.data import TrainingData
from edmcgs.model.eval.evaluation import FrameScore
from edmcgs.model.eval.metrics import psnr, ssim_score
from edmcgs.model.online.bounds import integrate

BASELINES = ("hold last anchor", "blend of neighbouring anchors", "events integrated onto the last anchor")
SHORT = dict(zip(BASELINES, ("hold_last", "blend", "integrate"), strict=True))
"""Column names of the baselines (CSV)."""
DEFAULT_CONTRAST = 0.2
"""C assumed when the recording does not state it (a DAVIS346's usual bias setting)."""


def baseline_image(data: TrainingData, t_us: int, name: str) -> tuple[np.ndarray, int]:
    """(float32 [H, W, C] image in [0, 1], the anchor time it starts from) of baseline ``name`` at t.
    Before the first anchor each holds the first; without events the integration holds the last."""
    times = data.anchors_t_us
    k = max(int(np.searchsorted(times, t_us, side="right")) - 1, 0)
    image = data.anchor_images[k].astype(np.float32) / 255.0
    if name == BASELINES[1] and k + 1 < len(times) and t_us > times[k]:
        w = (t_us - int(times[k])) / (int(times[k + 1]) - int(times[k]))
        image = (1.0 - w) * image + w * (data.anchor_images[k + 1].astype(np.float32) / 255.0)
    elif name == BASELINES[2] and data.event_map is not None and t_us > times[k]:
        contrast = DEFAULT_CONTRAST if data.contrast_threshold is None else data.contrast_threshold
        image = integrate(image, data.event_map(int(times[k]), int(t_us)), contrast)
    elif name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; one of {BASELINES}")
    return image, int(times[k])


def score_baselines(data: TrainingData, indices: np.ndarray | None = None) -> dict[str, list[FrameScore]]:
    """Each baseline scored on the held-out frames ``indices`` (default: all evaluable ones)."""
    indices = data.evaluable() if indices is None else np.asarray(indices)
    out: dict[str, list[FrameScore]] = {}
    for name in BASELINES:
        rows = []
        for i in indices.tolist():
            t = int(data.held_out_t_us[i])
            image, tau = baseline_image(data, t, name)
            target = data.held_out_images[i].astype(np.float32) / 255.0
            rows.append(FrameScore(i, t, tau, 0, psnr(image, target), ssim_score(image, target),
                                   ssim_3dgs=ssim_score(image, target, "3dgs")))
        out[name] = rows
    return out
