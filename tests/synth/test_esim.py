"""The event simulator against the event generation model, and its options."""

import math

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.events import Events
from edmcgs.synth.esim import (
    AdaptiveSampling,
    EventSimulator,
    SimulatorConfig,
    log_luminance,
    luminance,
    simulate_frames,
    simulate_render,
)

C = 0.2
EPS = 1e-3


def _random_walk_frames(n=40, h=6, w=7, seed=0):
    """Grey frames whose log luminance random-walks with steps of up to a few C (multiple crossings)."""
    rng = np.random.default_rng(seed)
    log_i = np.log(0.3) + np.cumsum(rng.normal(0, 0.4, size=(n, h, w)), axis=0)
    frames = np.clip(np.exp(log_i), 0.0, 1.0)
    t = np.cumsum(rng.integers(50, 3000, size=n)).astype(np.int64)
    return t, frames


def _polarity_sum(ev, h, w, t_a, t_b):
    """Signed polarity sum per pixel over (t_a, t_b]."""
    sel = (ev.t > t_a) & (ev.t <= t_b)
    out = np.zeros((h, w))
    np.add.at(out, (ev.y[sel], ev.x[sel]), ev.p[sel])
    return out


def test_event_generation_model_holds_at_every_sample():
    t, frames = _random_walk_frames()
    ev = simulate_frames(t, frames, SimulatorConfig(contrast_threshold=C, eps=EPS))
    h, w = frames.shape[1:]
    log_l = np.log(frames + EPS)
    assert len(ev) > 500
    for b in range(1, len(t)):
        # from the start (references = L(t0)) the error is one threshold at most ...
        err = C * _polarity_sum(ev, h, w, t[0], t[b]) - (log_l[b] - log_l[0])
        assert np.abs(err).max() < C + 1e-9
        # ... and over any window between samples, two (one reference offset at each end)
        a = b // 2
        err = C * _polarity_sum(ev, h, w, t[a], t[b]) - (log_l[b] - log_l[a])
        assert np.abs(err).max() < 2 * C + 1e-9


def test_events_are_time_ordered_and_inside_their_steps():
    t, frames = _random_walk_frames(n=15, h=20, w=30, seed=3)
    sim = EventSimulator(SimulatorConfig(eps=EPS))
    sim.reset(int(t[0]), frames[0])
    for t0, t1, frame in zip(t[:-1], t[1:], frames[1:], strict=True):
        ev = sim.step(int(t1), frame)
        assert len(ev) > 0
        assert np.all(np.diff(ev.t) >= 0)
        assert ev.t.min() > t0 and ev.t.max() <= t1
        assert ev.t.dtype == np.int64 and ev.x.dtype == np.uint16 and ev.p.dtype == np.int8


def test_a_jump_over_several_thresholds_fires_one_event_per_threshold_at_interpolated_times():
    lo, hi = 0.1, 0.9
    frames = np.array([[[lo]], [[hi]], [[lo]]])
    t = np.array([1_000_000, 1_001_000, 1_002_000], np.int64)
    ev = simulate_frames(t, frames, SimulatorConfig(contrast_threshold=C, eps=EPS))
    delta = np.log(hi + EPS) - np.log(lo + EPS)
    n = int(np.floor(delta / C))
    up, down = ev.p[ev.t <= t[1]], ev.p[ev.t > t[1]]
    assert list(up) == [1] * n
    # going back down crosses from the last reference (lo + n C) down to lo: n events again
    assert list(down) == [-1] * n
    expected = t[0] + np.ceil(np.arange(1, n + 1) * C / delta * 1000).astype(np.int64)
    np.testing.assert_array_equal(ev.t[:n], expected)


def test_saturated_black_and_white_frames_stay_finite():
    black = np.zeros((4, 5, 3), np.uint8)
    white = np.full((4, 5, 3), 255, np.uint8)
    assert np.isfinite(log_luminance(black, EPS)).all()
    ev = simulate_frames(np.array([0, 10, 20], np.int64), [black, white, black], SimulatorConfig(eps=EPS))
    per_pixel = int(np.floor((np.log(1 + EPS) - np.log(EPS)) / C))
    assert len(ev) == 2 * per_pixel * 20
    assert np.all(np.isfinite(ev.t))
    # float frames beyond [0, 1] (HDR white, negative noise) are handled too
    ev = simulate_frames(np.array([0, 10], np.int64), [np.full((2, 2), -0.5), np.full((2, 2), 3.0)])
    assert len(ev) == 4 * int(np.floor((np.log(3 + 1e-3) - np.log(1e-3)) / 0.2))


def test_luminance_weights_rgb_and_keeps_grey():
    rgb = np.zeros((1, 3, 3), np.float32)
    rgb[0, 0, 0] = rgb[0, 1, 1] = rgb[0, 2, 2] = 1.0
    np.testing.assert_allclose(luminance(rgb)[0], [0.299, 0.587, 0.114], rtol=1e-6)
    grey = np.array([[0, 51, 255]], np.uint8)
    np.testing.assert_allclose(luminance(grey)[0], [0.0, 0.2, 1.0])
    np.testing.assert_allclose(log_luminance(grey[..., None], 0.5)[0], np.log([0.5, 0.7, 1.5]))


def _ramp(n=20, h=10, w=12):
    """Every pixel brightens by the same amount: log luminance rises by 0.15 per frame."""
    levels = np.exp(np.log(0.01) + 0.15 * np.arange(n))
    frames = np.broadcast_to(levels[:, None, None], (n, h, w)).copy()
    return np.arange(n, dtype=np.int64) * 1000, frames


def test_threshold_mismatch_varies_counts_per_pixel_and_is_seeded():
    t, frames = _ramp()
    ideal = simulate_frames(t, frames, SimulatorConfig(eps=0.0 + 1e-9))
    counts = np.bincount(ideal.y.astype(int) * 12 + ideal.x, minlength=120)
    assert counts.min() == counts.max()  # no mismatch: every pixel alike
    cfg = SimulatorConfig(threshold_sigma=0.05, seed=7, eps=1e-9)
    a, b = simulate_frames(t, frames, cfg), simulate_frames(t, frames, cfg)
    assert a == b
    counts = np.bincount(a.y.astype(int) * 12 + a.x, minlength=120)
    assert counts.max() > counts.min() + 2
    assert simulate_frames(t, frames, SimulatorConfig(threshold_sigma=0.05, seed=8, eps=1e-9)) != a
    sim = EventSimulator(SimulatorConfig(threshold_sigma=1.0, min_threshold=0.03))
    sim.reset(0, frames[0])
    assert min(c.min() for c in sim.thresholds) >= 0.03


def test_refractory_period_spaces_each_pixels_events():
    t, frames = _random_walk_frames(n=30, h=5, w=5, seed=1)
    free = simulate_frames(t, frames, SimulatorConfig(eps=EPS))
    held = simulate_frames(t, frames, SimulatorConfig(eps=EPS, refractory_us=2000))
    assert 0 < len(held) < len(free)
    for pix in range(25):
        times = held.t[(held.y.astype(int) * 5 + held.x) == pix]
        assert np.all(np.diff(times) >= 2000)


def test_background_noise_follows_its_rate_and_seed():
    frames = np.full((2, 40, 50), 0.5)
    t = np.array([0, 2_000_000], np.int64)
    cfg = SimulatorConfig(noise_rate_hz=0.5, seed=3)
    ev = simulate_frames(t, frames, cfg)
    mean = 0.5 * 40 * 50 * 2.0
    assert abs(len(ev) - mean) < 5 * np.sqrt(mean)
    assert ev.t.min() > 0 and ev.t.max() <= 2_000_000 and np.all(np.diff(ev.t) >= 0)
    assert set(np.unique(ev.p)) == {-1, 1}
    assert simulate_frames(t, frames, cfg) == ev
    assert simulate_frames(t, frames, SimulatorConfig(noise_rate_hz=0.5, seed=4)) != ev
    assert len(simulate_frames(t, frames, SimulatorConfig())) == 0


def test_bad_input_is_rejected_with_the_parameter_named():
    with pytest.raises(InvalidInputError, match="contrast_threshold"):
        SimulatorConfig(contrast_threshold=0.0)
    with pytest.raises(InvalidInputError, match="refractory_us"):
        SimulatorConfig(refractory_us=-1)
    with pytest.raises(InvalidInputError, match="NaN"):
        log_luminance(np.array([[0.5, np.nan]]))
    sim = EventSimulator()
    with pytest.raises(InvalidInputError, match="reset"):
        sim.step(10, np.zeros((2, 2)))
    sim.reset(10, np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="after the last sample"):
        sim.step(10, np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="shape"):
        sim.step(20, np.zeros((3, 2)))
    with pytest.raises(InvalidInputError, match="t_us must be an integer"):
        sim.step(20.5, np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="strictly increasing"):
        simulate_frames(np.array([0, 0]), np.zeros((2, 2, 2)))


def _moving_edge(t_us: int) -> np.ndarray:
    """A soft vertical edge that sits still for 20 ms, then sweeps across 16 px in 10 ms."""
    pos = 4 + 16 * np.clip((t_us - 20_000) / 10_000, 0, 1)
    x = np.arange(24)[None, :]
    return np.broadcast_to(0.1 + 0.8 / (1 + np.exp(-(x - pos))), (6, 24))


def test_adaptive_sampling_refines_where_the_image_changes_fast():
    sampling = AdaptiveSampling(dt_max_us=2000, dt_min_us=50, max_delta=0.5)
    ev, samples = simulate_render(_moving_edge, 0, 40_000, SimulatorConfig(eps=EPS), sampling)
    steps = np.diff(samples)
    assert samples[0] == 0 and samples[-1] == 40_000 and np.all(steps > 0)
    still = steps[samples[1:] <= 20_000]
    moving = steps[(samples[1:] > 20_500) & (samples[1:] <= 30_000)]
    assert still.min() == 2000 and moving.max() < 500
    # each accepted step changes L by at most max_delta * C unless it hit dt_min
    log_l = np.stack([log_luminance(_moving_edge(int(s)), EPS) for s in samples])
    change = np.abs(np.diff(log_l, axis=0)).max(axis=(1, 2))
    assert np.all((change <= 0.5 * C + 1e-12) | (steps <= 50))
    # the same events as the plain frame path on those sample times
    assert ev == simulate_frames(samples, [_moving_edge(int(s)) for s in samples], SimulatorConfig(eps=EPS))
    err = C * _polarity_sum(ev, 6, 24, 0, 40_000) - (log_l[-1] - log_l[0])
    assert np.abs(err).max() < C


def test_parallel_passes_give_the_same_events():
    t, frames = _random_walk_frames(n=12, h=30, w=41, seed=5)
    cfg = SimulatorConfig(eps=EPS, refractory_us=500, threshold_sigma=0.05, seed=2)
    serial, parallel = EventSimulator(cfg), EventSimulator(cfg, parallel=True)
    serial.reset(int(t[0]), frames[0])
    parallel.reset(int(t[0]), frames[0])
    for t1, frame in zip(t[1:], frames[1:], strict=True):
        assert serial.step(int(t1), frame) == parallel.step(int(t1), frame)
    np.testing.assert_array_equal(log_luminance(frames[3], EPS), log_luminance(frames[3], EPS, parallel=True))


def _flat_run(config, h=40, w=50, seconds=1.0, step_us=10_000):
    """Events of a constant grey scene (no signal: only noise and hot pixels fire)."""
    sim = EventSimulator(config)
    frame = np.full((h, w), 0.4)
    sim.reset(0, frame)
    ev = [sim.step(t, frame) for t in range(step_us, round(seconds * 1e6) + 1, step_us)]
    return sim, Events.concat(ev)


def test_hot_pixels_fire_at_their_rate_and_only_there():
    config = SimulatorConfig(hot_pixel_fraction=0.01, hot_pixel_rate_hz=200.0, seed=4)
    sim, ev = _flat_run(config, seconds=2.0)
    ys, xs = sim.hot_pixels
    assert len(ys) == 20 and len(set(zip(ys.tolist(), xs.tolist(), strict=True))) == 20
    counts = np.zeros((40, 50), int)
    np.add.at(counts, (ev.y, ev.x), 1)
    hot = np.zeros((40, 50), bool)
    hot[ys, xs] = True
    assert counts[~hot].sum() == 0
    rate = counts[hot] / 2.0  # per pixel per second; each ~ Poisson(400) over 2 s
    assert abs(rate.mean() - 200.0) < 5 * math.sqrt(400 / 20) / 2.0 and rate.min() > 120
    assert np.all(np.diff(ev.t) >= 0) and set(np.unique(ev.p).tolist()) == {-1, 1}
    assert abs(np.mean(ev.p == 1) - 0.5) < 0.05
    # the same seed picks the same pixels; the default has none
    again, _ = _flat_run(config, seconds=0.02)
    np.testing.assert_array_equal(again.hot_pixels[0], ys)
    assert len(_flat_run(SimulatorConfig(), seconds=0.02)[0].hot_pixels[0]) == 0


def test_background_noise_has_its_rate_uniformly():
    sim, ev = _flat_run(SimulatorConfig(noise_rate_hz=5.0, seed=1), seconds=1.0)
    expected = 5.0 * 40 * 50  # 10k
    assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
    per_row = np.bincount(ev.y, minlength=40)
    assert per_row.min() > 0.6 * expected / 40 and per_row.max() < 1.4 * expected / 40
    assert len(sim.hot_pixels[0]) == 0


def test_hot_pixels_do_not_change_the_signal_events():
    t, frames = _random_walk_frames(n=10, h=8, w=9, seed=2)
    base = SimulatorConfig(threshold_sigma=0.03, noise_rate_hz=3.0, seed=5)
    plain = simulate_frames(t, frames, base)
    hot = simulate_frames(t, frames, SimulatorConfig(**(base.to_metadata() | {
        "hot_pixel_fraction": 0.05, "hot_pixel_rate_hz": 500.0})))
    sim = EventSimulator(SimulatorConfig(hot_pixel_fraction=0.05, seed=5))
    sim.reset(0, frames[0])
    ys, xs = sim.hot_pixels
    keep = ~np.isin(hot.y.astype(int) * 9 + hot.x, ys * 9 + xs)
    keep_plain = ~np.isin(plain.y.astype(int) * 9 + plain.x, ys * 9 + xs)
    np.testing.assert_array_equal(np.sort(hot.t[keep]), np.sort(plain.t[keep_plain]))
    assert len(hot) > len(plain)
