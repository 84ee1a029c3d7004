"""Unix-epoch microsecond timestamps over a 24-hour recording (about 1.7e15 µs, which float32 cannot hold):
the model's time normalisation, tau, the event ring's windows, the trajectory and the training grid
resolve single microseconds. (Epoch times in the ring and trajectory at short spans: tests/sensor/
test_ring.py, tests/camera/test_camera.py::
test_trajectory_interpolates_slerp_and_linear_in_int64_microseconds.)

The model's networks take the normalised time as float32; over 24 h that input resolves about
86400 s / 2^24 = 5 ms (the report states this), while every window and anchor decision is exact.
"""

import itertools

import numpy as np
import torch

from edmcgs.geometry import Trajectory, pose_from_quat
from edmcgs.model.data import EventGrid, TrainingData
from edmcgs.model.dynamic import EdMCGS
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.events import Events
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY

T0 = 1_700_000_000_000_000
DAY = 86_400_000_000
ANCHORS = np.array([T0, T0 + DAY // 2, T0 + DAY], np.int64)


def test_float32_cannot_hold_epoch_microseconds():
    assert np.float32(T0) == np.float32(T0 + 1) == np.float32(T0 + 64)  # the premise of this file


def _day_model() -> EdMCGS:
    img = tiny_scene.to_uint8(tiny_scene.image(tiny_scene.T0))
    poses = np.repeat(np.eye(4)[None], 3, 0)
    return EdMCGS.from_arrays(anchors_t_us=ANCHORS, anchor_images=np.stack([img] * 3),
                              intrinsics=tiny_scene.INTRINSICS, anchor_poses=poses, config=TINY)


def test_normalised_time_and_tau_resolve_one_microsecond_over_a_day():
    meta = _day_model().meta
    assert meta.normalized_time(T0) == 0.0 and meta.normalized_time(T0 + DAY) == 1.0
    assert meta.normalized_time(T0 + DAY // 2) == 0.5 and meta.normalized_time(T0 + DAY // 4) == 0.25
    for t in (T0, T0 + 1, T0 + DAY // 2 - 1, T0 + DAY - 2):
        a, b = meta.normalized_time(t), meta.normalized_time(t + 1)
        assert b > a
        np.testing.assert_allclose(b - a, 1 / DAY, rtol=1e-4)  # float64 spacing near 1 is 1.1e-16
    model = _day_model()
    assert model.tau(T0 + DAY // 2 - 1) == T0 and model.tau(T0 + DAY // 2) == T0 + DAY // 2
    assert model.tau(T0 + DAY) == T0 + DAY


def test_deform_at_epoch_times_a_day_apart_is_finite():
    model = _day_model()
    randomize_event_branch(model)
    emap = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
    emap[10:20, 20:30] = 2.0
    for t in (T0 + 1, T0 + DAY // 2 + 1, T0 + DAY - 1):
        state = model.deform(t, emap)
        assert torch.isfinite(state.means).all() and torch.isfinite(state.quats).all()


def test_ring_windows_one_microsecond_apart_at_the_end_of_a_day():
    ring = EventRingBuffer(64)
    end = T0 + DAY
    t = np.array([T0, end - 3, end - 2, end - 1, end], np.int64)
    ring.push(Events(t, [0, 1, 2, 3, 4], [0] * 5, [1, -1, 1, -1, 1]), complete_until_us=end + 1)
    for i, ti in enumerate(t.tolist()):
        window = ring.slice(ti, ti + 1)  # half-open: exactly the event at ti
        assert window.t.tolist() == [ti] and window.x.tolist() == [i]
    assert ring.count(end - 2, end) == 2 and ring.count(T0 + 1, end - 3) == 0


def test_trajectory_over_a_day_moves_between_single_microseconds():
    # 86.4 m and a quarter turn over 24 h: 1e-9 m per microsecond.
    q = [np.cos(np.pi / 8), 0.0, np.sin(np.pi / 8), 0.0]
    traj = Trajectory(np.array([T0, T0 + DAY], np.int64),
                      np.stack([pose_from_quat([0, 0, 0], [1, 0, 0, 0]), pose_from_quat([86.4, 0, 0], q)]))
    for t in (T0, T0 + DAY // 3, T0 + DAY - 1):
        step = traj.at(t + 1)[:3, 3] - traj.at(t)[:3, 3]
        np.testing.assert_allclose(step, [1e-9, 0, 0], rtol=1e-3, atol=1e-15)
    np.testing.assert_array_equal(traj.at(T0 + DAY), traj.c2w[1])


def test_training_grid_over_a_day_is_exact_integer_microseconds():
    img = tiny_scene.to_uint8(tiny_scene.image(tiny_scene.T0))
    poses = np.repeat(np.eye(4)[None], 3, 0)
    calls = []

    def event_map(t0: int, t1: int) -> np.ndarray:
        calls.append((t0, t1))
        return np.zeros((tiny_scene.H, tiny_scene.W), np.float32)

    data = TrainingData(anchors_t_us=ANCHORS, anchor_images=np.stack([img] * 3), anchor_poses=poses,
                        intrinsics=tiny_scene.INTRINSICS, trajectory=Trajectory(ANCHORS, poses),
                        t_end_us=T0 + DAY, event_map=event_map)
    grid = EventGrid.build(data, substeps=7)
    assert grid.times.dtype == np.int64
    np.testing.assert_array_equal(grid.times[:, 0], ANCHORS[:2])
    np.testing.assert_array_equal(grid.times[:, -1], ANCHORS[1:])
    assert calls == []  # a gap's sums are made when a step first needs them
    for gap in range(grid.num_gaps):
        grid.cumulative(gap)
    # consecutive windows tile each gap without a gap or an overlap of even one microsecond
    assert calls[0][0] == T0 and calls[-1][1] == T0 + DAY and len(calls) == 2 * 7
    assert all(a1 == b0 for (_, a1), (b0, _) in itertools.pairwise(calls))
    assert all(isinstance(v, int) and t0 < t1 for t0, t1 in calls for v in (t0, t1))
