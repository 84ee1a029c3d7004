"""Event windows at the extremes: empty, a burst of 10^7 events, hot-pixel noise only.

Already covered elsewhere (not repeated here): an empty window at an anchor is the anchor state
exactly (tests/model/test_model.py::test_empty_window_at_an_anchor_is_exactly_the_anchor_state),
10^7 events on one pixel accumulate exactly (tests/sensor/test_event_map.py::
test_ten_million_events_on_one_pixel_are_exact), and events reach only the control points within
Phi's receptive field (tests/model/test_model.py::test_event_branch_is_local).
"""

import math

import numpy as np
import pytest
import torch

from edmcgs.geometry import project
from edmcgs.model.data import TrainingData
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.motion.event_branch import FIELD
from edmcgs.model.train.trainer import Trainer
from edmcgs.pipeline import new_model
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, build, states_equal

MID_GAP = tiny_scene.T0 + 50_000  # between the first two anchors (0 and 100 ms)


def _trained_like_model() -> EdMCGS:
    model, _ = build(TINY.replace(event_pool=1))  # a 23-px field: local within this 48x32 image
    randomize_event_branch(model)
    with torch.no_grad():
        for p in model.prior.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    return model


def _assert_finite_and_bounded(model: EdMCGS, state) -> None:
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.isfinite(getattr(state, name)).all(), name
    for fast in (True, False):
        img = model.render(state, np.eye(4), model.meta.intrinsics, fast=fast)
        assert img.shape == (tiny_scene.H, tiny_scene.W, 3)
        assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0


def test_empty_window_between_anchors_adds_exactly_nothing():
    model = _trained_like_model()
    zeros = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
    prior_only = model.deform(MID_GAP)
    assert states_equal(prior_only, model.deform(MID_GAP, zeros))
    empty = accumulate(Events.empty(), tiny_scene.W, tiny_scene.H)
    assert states_equal(prior_only, model.deform(MID_GAP, empty))
    trans, _, event_disp = model.control_motion(0.25, torch.from_numpy(zeros), torch.eye(4))
    assert event_disp is None and torch.isfinite(trans).all()


def _burst(n: int, *, one_pixel: bool, seed: int = 0) -> Events:
    """n events in one millisecond at Unix-epoch time, 70 % positive, on one pixel or over the frame."""
    rng = np.random.default_rng(seed)
    t = MID_GAP - 1000 + np.arange(n, dtype=np.int64) * 1000 // n  # sorted, 1 ms
    if one_pixel:
        x, y = np.full(n, 20, np.uint16), np.full(n, 15, np.uint16)
    else:
        x = rng.integers(0, tiny_scene.W, n).astype(np.uint16)
        y = rng.integers(0, tiny_scene.H, n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.7, 1, -1).astype(np.int8)
    return Events(t, x, y, p)


@pytest.mark.parametrize("one_pixel", [False, True])
def test_a_burst_of_ten_million_events_sums_exactly_and_deforms_finite(one_pixel):
    n = 10_000_000
    ev = _burst(n, one_pixel=one_pixel)
    emap = accumulate(ev, tiny_scene.W, tiny_scene.H)
    # I_E is an exact integer sum per pixel (float32 holds every integer below 2^24).
    flat = ev.y.astype(np.int64) * tiny_scene.W + ev.x
    size = tiny_scene.W * tiny_scene.H
    signed = np.bincount(flat[ev.p > 0], minlength=size) - np.bincount(flat[ev.p < 0], minlength=size)
    np.testing.assert_array_equal(emap.reshape(-1).astype(np.int64), signed)
    assert int(emap.astype(np.float64).sum()) == int((ev.p > 0).sum()) - int((ev.p < 0).sum())
    model = _trained_like_model()
    state = model.deform(MID_GAP, emap)
    _assert_finite_and_bounded(model, state)
    assert not states_equal(state, model.deform(MID_GAP))  # the burst does drive the transition


def test_hot_pixel_noise_only_stays_finite_and_local():
    """Five hot pixels firing thousands of alternating events each, nothing else, in every window."""
    hot = [(3, 3), (44, 4), (40, 28), (5, 29), (24, 16)]
    counts = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
    for i, (x, y) in enumerate(hot):
        counts[y, x] = 4001.0 if i % 2 else -3999.0  # net sums of +-1 flicker at a hot pixel's rate

    def noise_map(t0: int, t1: int) -> np.ndarray:
        return counts * np.float32((t1 - t0) / 100_000)  # proportional to the window length

    model = _trained_like_model()
    state = model.deform(MID_GAP, noise_map(tiny_scene.T0, MID_GAP))
    _assert_finite_and_bounded(model, state)
    # Only the control points within Phi's receptive field of a hot pixel move.
    _, _, disp = model.control_motion(0.25, torch.from_numpy(noise_map(tiny_scene.T0, MID_GAP)), torch.eye(4))
    prior_trans, _, _ = model.control_motion(0.25)  # the points are sampled where the prior puts them
    uv, _ = project(model.control.positions + prior_trans, torch.eye(4), model.meta.intrinsics)
    near = torch.zeros(len(uv), dtype=torch.bool)
    for x, y in hot:
        near |= ((uv[:, 0] - x).abs() <= FIELD + 1) & ((uv[:, 1] - y).abs() <= FIELD + 1)
    assert torch.equal(disp[~near], torch.zeros_like(disp[~near]))
    assert torch.isfinite(disp).all()


def test_training_on_hot_pixel_noise_only_stays_finite():
    """A static scene whose only events are hot-pixel noise: the event loss fights noise, nothing blows up."""
    base = tiny_scene.data(x0=10.0, x1=10.0)  # the square does not move
    rng = np.random.default_rng(3)
    hot = rng.integers(0, [tiny_scene.W, tiny_scene.H], size=(8, 2))

    def noise_map(t0: int, t1: int) -> np.ndarray:
        out = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
        out[hot[:, 1], hot[:, 0]] = np.float32((t1 - t0) // 100)  # one net event per 100 µs per pixel
        return out

    data = TrainingData(anchors_t_us=base.anchors_t_us, anchor_images=base.anchor_images,
                        anchor_poses=base.anchor_poses, intrinsics=base.intrinsics,
                        trajectory=base.trajectory, t_end_us=base.t_end_us, event_map=noise_map)
    cfg = TINY.replace(iterations=10, event_warmup=(0.0, 0.1), densify_from=0.9)
    model = new_model(data, cfg)
    trainer = Trainer(model, data, progress=False)
    for _ in range(cfg.iterations):
        out = trainer.train_step()
        assert all(math.isfinite(v) for v in out.values()), out
        assert out["event"] > 0  # the noise is never explained by the static renders
    model.eval()
    _assert_finite_and_bounded(model, model.deform(MID_GAP, noise_map(tiny_scene.T0, MID_GAP)))
