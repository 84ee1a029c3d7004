"""The trivial baselines: integrating events onto the last anchor follows the sensor's own model."""

import numpy as np

from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.model.data import TrainingData
from edmcgs.model.eval import baselines as b
from edmcgs.model.eval.baselines import BASELINES, baseline_image, score_baselines
from edmcgs.model.online.bounds import integrate

INTEGRATE = BASELINES[2]


def _data(contrast, events: bool = True) -> tuple[TrainingData, list]:
    """Two anchors 100 ms apart on a 4x4 grey image; the middle pixel brightens by 5 events between
    them (a log-intensity ramp); held-out frames every 20 ms follow the same model."""
    c = b.DEFAULT_CONTRAST if contrast is None else contrast
    start = np.full((4, 4), 0.3)
    calls = []

    def counts(t0: int, t1: int) -> np.ndarray:
        calls.append((t0, t1))
        m = np.zeros((4, 4), np.float32)
        m[1, 2] = np.floor(5 * (min(t1, 100_000) - t0) / 100_000)
        return m

    def frame(t: int) -> np.ndarray:
        return np.round(255 * integrate(start[..., None], counts(0, t), c)).astype(np.uint8)

    held = np.array([20_000, 40_000, 60_000, 80_000], np.int64)
    data = TrainingData(
        anchors_t_us=np.array([0, 100_000], np.int64), anchor_images=np.stack([frame(0), frame(100_000)]),
        anchor_poses=np.stack([np.eye(4)] * 2), intrinsics=Intrinsics(4.0, 4.0, 1.5, 1.5, 4, 4),
        trajectory=Trajectory(np.array([0], np.int64), np.eye(4)[None]), t_end_us=100_000,
        event_map=counts if events else None, held_out_t_us=held,
        held_out_images=np.stack([frame(int(t)) for t in held]), contrast_threshold=contrast)
    calls.clear()
    return data, calls


def test_integration_reads_the_events_since_the_anchor_and_beats_hold_on_its_own_model():
    for contrast in (0.35, None):  # the recording's C, or the default when it states none
        data, calls = _data(contrast)
        scores = score_baselines(data)
        assert calls == [(0, int(t)) for t in data.held_out_t_us]  # [tau, t) of each held-out frame
        assert min(s.psnr for s in scores[INTEGRATE]) > 45
        assert np.mean([s.psnr for s in scores[INTEGRATE]]) > np.mean([s.psnr for s in scores[BASELINES[0]]])


def test_without_events_integration_holds_the_last_anchor():
    data, _ = _data(0.2, events=False)
    for t in data.held_out_t_us.tolist():
        held, tau = baseline_image(data, t, BASELINES[0])
        got, tau_i = baseline_image(data, t, INTEGRATE)
        assert tau == tau_i and np.array_equal(got, held)
