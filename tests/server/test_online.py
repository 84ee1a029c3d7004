"""Online anchors (server/live/, model/online/): frames past the checkpoint's span become anchors,
predicted by the event transition and corrected in the background; bad frames are refused and counted,
a fit that falls behind skips and counts, the store stays bounded, and the engine renders up to the head."""

from __future__ import annotations

import copy
import threading
from dataclasses import replace

import numpy as np
import pytest
import torch

from edmcgs.geometry import Trajectory
from edmcgs.model import online as model_online
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.online.bounds import integrate
from edmcgs.model.render.sh import SH_C0
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.sensor.frames import Frames
from edmcgs.server.engine import CAMERA_POSE_ATOL, Engine
from edmcgs.server.live.anchors import OnlineAnchors
from edmcgs.server.live.clock import Timeline
from edmcgs.server.live.config import OnlineConfig
from edmcgs.server.live.timebase import Timebase
from harness.server import build_scene

STEP_US = 50_000


@pytest.fixture(scope="module")
def long_scene(tmp_path_factory):
    """A 2.5 s recording at 64x48, frames every 50 ms; the checkpoint covers its first 0.5 s."""
    rec_path, ckpt = build_scene(tmp_path_factory.mktemp("online"), width=64, height=48, duration_s=2.5,
                                 anchor_every_s=0.1, frames_per_anchor=2, event_rate=20_000, init_points=1000,
                                 control_points=32, event_branch_seed=0, train_s=0.5)
    from edmcgs.sensor.files.recording import read_recording

    return read_recording(rec_path), load_checkpoint(ckpt)


def _events(t0: int, t1: int, n: int = 400, seed: int = 0) -> Events:
    rng = np.random.default_rng(seed)
    return Events(np.sort(rng.integers(t0, t1, n)).astype(np.int64),
                  rng.integers(0, 64, n).astype(np.uint16), rng.integers(0, 48, n).astype(np.uint16),
                  np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8))


def _feed(online: OnlineAnchors, ring: EventRingBuffer, rec, until_us: int, timeline: Timeline,
          from_us: int | None = None) -> None:
    """Push the recording's events and frames up to ``until_us`` as the ingest thread does."""
    lo = rec.t_range_us[0] if from_us is None else from_us
    ring.push(rec.events.time_slice(lo, until_us), complete_until_us=until_us)
    sel = (rec.anchors.t_us >= lo) & (rec.anchors.t_us < until_us)
    online.on_frames(Frames(rec.anchors.t_us[sel], rec.anchors.images[sel], rec.anchors.poses[sel]),
                     timeline.scene_of)


def test_frames_past_the_span_become_predicted_anchors_chained_by_the_events(long_scene):
    rec, model = long_scene
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    start = rec.t_range_us[0]
    tl = Timeline(start, start)
    _feed(online, ring, rec, model.meta.t_end_us + 3 * STEP_US + 1, tl)
    anchors = online.anchors()
    assert [a.t_us - model.meta.t_end_us for a in anchors] == [STEP_US, 2 * STEP_US, 3 * STEP_US]
    assert not any(a.corrected for a in anchors)
    # the first from the checkpoint's last anchor: what deform gives there (the prior clamped at the end)
    last = int(model.meta.anchors_us[-1])
    emap = accumulate(rec.events.time_slice(last, anchors[0].t_us), 64, 48)
    pose = rec.anchors.poses[rec.anchors.t_us == anchors[0].t_us][0]
    expected = model.deform(anchors[0].t_us, emap, ev_c2w=pose)
    got = model_online.state_of(model, anchors[0].motion)
    torch.testing.assert_close(got.means, expected.means, atol=1e-5, rtol=0)
    # the next one moved from the first by g_phi of the events in between
    assert not torch.equal(anchors[1].motion[0], anchors[0].motion[0])
    assert online.tau(anchors[1].stream_us + 10, anchors[1].t_us + 10) == anchors[1].stream_us
    assert online.tau(model.meta.t_end_us + 10, model.meta.t_end_us + 10) == last


def test_bad_frames_are_refused_and_counted(long_scene):
    rec, model = long_scene
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    tl = Timeline(rec.t_range_us[0], rec.t_range_us[0])
    end = model.meta.t_end_us
    ring.push(_events(end - 100_000, end + 400_000), complete_until_us=end + 400_000)
    good = np.zeros((48, 64, 3), np.uint8)
    online.on_frames(Frames(np.array([end + 100_000], np.int64), good[None]), tl.scene_of)
    online.on_frames(Frames(np.array([end + 200_000], np.int64), np.zeros((1, 40, 64, 3), np.uint8)),
                     tl.scene_of)
    online.on_frames(Frames(np.array([end + 50_000], np.int64), good[None]), tl.scene_of)  # older
    online.on_frames(Frames(np.array([end + 100_000], np.int64), good[None]), tl.scene_of)  # the same
    online.on_frames(Frames(np.array([end + 300_000], np.int64), np.zeros((1, 48, 64, 1), np.uint8)),
                     tl.scene_of)
    assert online.refused == {"size": 1, "channels": 1, "timestamp": 2}
    assert [a.t_us for a in online.anchors()] == [end + 100_000]


def test_the_store_is_bounded_and_expires_with_the_events(long_scene):
    rec, model = long_scene
    tl = Timeline(rec.t_range_us[0], rec.t_range_us[0])
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(capacity=4, fit=False))
    _feed(online, ring, rec, rec.t_range_us[1], tl)
    assert len(online.anchors()) == 4 and online.expired == online.predicted - 4 > 0
    # a ring holding ~150 ms of events: anchors go with their events
    ring = EventRingBuffer(3000)
    online = OnlineAnchors(model, ring, OnlineConfig(capacity=64, fit=False))
    lo = rec.t_range_us[0]
    for hi in range(lo + STEP_US, rec.t_range_us[1], STEP_US):
        _feed(online, ring, rec, hi, tl, from_us=hi - STEP_US)
    assert ring.stats().overflowed > 0 and online.restarted == 0
    assert 0 < len(online.anchors()) < online.predicted == 38
    assert all(a.stream_us > ring.stats().oldest_us for a in online.anchors())


def test_a_chain_whose_events_are_gone_starts_again_and_renders_to_the_head(long_scene):
    """Frames past the span whose events since the anchor before left the ring (or span more than a
    second: a learnt model far behind the head) start the chain again at their own time, so the head
    still renders; without them the chain stayed dead."""
    rec, model = long_scene
    start = rec.t_range_us[0]
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    engine.timeline = tl = Timeline(start, start)
    late = int(model.meta.t_end_us) + 1_200_000  # more than a second past the span's last anchor
    # the ring holds the events of the last 0.3 s only; frames from ``late`` on
    ring.push(rec.events.time_slice(late - 300_000, late + 400_000), complete_until_us=late + 400_000)
    sel = (rec.anchors.t_us >= late) & (rec.anchors.t_us < late + 400_000)
    online.on_frames(Frames(rec.anchors.t_us[sel], rec.anchors.images[sel], rec.anchors.poses[sel]),
                     tl.scene_of)
    assert online.restarted == 1 and online.predicted == int(sel.sum()) > 1
    out = engine.render(None, None, 64, 48)
    assert out.anchor == "predicted" and out.instant.anchor_us == online.anchors()[-1].t_us
    restart = online.anchors()[0]
    want = model_online.checkpoint_motion(model, restart.t_us)
    assert all(torch.equal(a, b) for a, b in zip(restart.motion, want, strict=True))


def test_a_fit_that_falls_behind_skips_and_counts_and_corrections_publish(long_scene):
    rec, model = long_scene
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit_steps=3, fit_scale=0.5, colour_lr=0.0))
    gate = threading.Event()
    correct = model_online.correct

    def slow(*args, **kwargs):
        gate.wait(10)
        return correct(*args, **kwargs)

    model_online.correct = slow
    try:
        online.start()
        tl = Timeline(rec.t_range_us[0], rec.t_range_us[0])
        _feed(online, ring, rec, rec.t_range_us[1] + 1, tl)
        n = online.predicted
        assert n == 40 and online.queue_depth == 2  # one fitting (held), one waiting: never more
        gate.set()
        assert online.wait_idle(60)
    finally:
        model_online.correct = correct
        online.stop()
    # one was taken by the (held) fit, the newest waited; every other one was superseded
    assert online.skipped["superseded"] == n - 2 and online.corrected == 2
    corrected = [a for a in online.anchors() if a.corrected]
    assert len(corrected) == 2 and corrected[-1] is online.anchors()[-1]
    # the first correction is carried on to every anchor predicted after it
    later = [a for a in online.anchors() if a.stream_us >= corrected[0].stream_us]
    assert all(a.version >= 1 for a in later)
    before, after = online.last_loss
    assert after <= before


def _engine_past_the_span(rec, model) -> tuple[Engine, OnlineAnchors, int]:
    """An engine with predicted online anchors (no fits) fed up to a head five frames past the span."""
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    start = rec.t_range_us[0]
    engine.timeline = tl = Timeline(start, start)
    head = model.meta.t_end_us + 5 * STEP_US + 20_000
    _feed(online, ring, rec, head + 1, tl)
    return engine, online, head


def test_the_engine_renders_past_the_span_up_to_the_head(long_scene):
    rec, model = long_scene
    engine, online, head = _engine_past_the_span(rec, model)
    start = rec.t_range_us[0]
    assert engine.renderable() == [(start, head)]
    assert [s for s, *_ in engine.timebase.rule.ranges(head)] == ["checkpoint", "online"]
    out = engine.render(None, None, 64, 48)
    assert out.instant.t_us == head and out.anchor == "predicted"
    assert out.instant.anchor_us == online.anchors()[-1].t_us and out.events > 0
    before = engine.render(model.meta.t_end_us + 10_000, None, 64, 48)
    assert before.anchor == "checkpoint" and before.instant.anchor_us == int(model.meta.anchors_us[-1])


def _assert_projected(engine, model, t_us, frame) -> None:
    """A render of the camera's view at t_us lies within one threshold of ``frame`` moved by the events
    of its window (uint8 rounding), and is the model's render alone clipped into those bounds."""
    out = engine.render(t_us, None, 64, 48)
    assert out.projected and "project" in out.stages
    emap = accumulate(engine.ring.slice(*out.instant.window), 64, 48)
    assert np.abs(emap).sum() > 0  # the events move the bounds
    c, eps = model.config.contrast_threshold, model.config.log_eps
    lo = integrate(frame / 255.0, emap, c, shift=-c, eps=eps)
    hi = integrate(frame / 255.0, emap, c, shift=c, eps=eps)
    pixels = out.pixels / 255.0
    assert (pixels >= lo - 0.5 / 255 - 1e-6).all() and (pixels <= hi + 0.5 / 255 + 1e-6).all()
    model_alone = engine.render(t_us, None, 64, 48, camera_view=False)
    assert not model_alone.projected and not np.array_equal(model_alone.pixels, out.pixels)
    assert np.abs(np.clip(model_alone.pixels / 255.0, lo, hi) - pixels).max() <= 1.0 / 255 + 1e-6


def test_the_event_cameras_view_past_the_span_is_projected_onto_the_events_since_its_frame(long_scene):
    rec, model = long_scene
    engine, online, head = _engine_past_the_span(rec, model)
    anchor = online.anchors()[-1]
    assert anchor.frame is not None and not anchor.frame.flags.writeable
    _assert_projected(engine, model, head, anchor.frame)
    out = engine.render(None, None, 64, 48)  # the head
    assert out.projected and out.anchor == "predicted"
    # past the span before the first online anchor: the stream's frame at the checkpoint's last anchor
    last = int(model.meta.anchors_us[-1])
    early = engine.render(model.meta.t_end_us + 10_000, None, 64, 48)
    assert early.anchor == "checkpoint" and early.instant.anchor_us == last
    _assert_projected(engine, model, model.meta.t_end_us + 10_000,
                      rec.anchors.images[int(np.searchsorted(rec.anchors.t_us, last))])
    # the event camera's own pose given is its view; any other pose is the model's alone
    pose = engine.default_pose(out.instant.t_us)
    model_alone = engine.render(None, None, 64, 48, camera_view=False)
    assert np.array_equal(engine.render(None, pose, 64, 48).pixels, out.pixels)
    rounded = pose.copy()
    rounded[:3] += 0.5 * CAMERA_POSE_ATOL
    assert engine.render(None, rounded, 64, 48).projected, "a round trip's rounding"
    other = pose.copy()
    other[0, 3] += 0.01
    assert not engine.render(None, other, 64, 48).projected
    assert engine.render(None, other, 64, 48, camera_view=True).projected, "the caller's word"
    # at another size the bounds are taken at each pixel's nearest frame and event pixel
    assert engine.render(None, None, 32, 24).projected
    # within the span, and with online_project off: the model alone
    assert not engine.render(model.meta.t_end_us - 10_000, None, 64, 48).projected
    online.config = replace(online.config, project=False)
    assert np.array_equal(engine.render(None, None, 64, 48).pixels, model_alone.pixels)


def test_a_moving_camera_past_its_learnt_poses_shows_the_frame_moved_by_the_events(long_scene):
    """A cold start's model, frames past its span with no pose, a camera whose trajectory moves: where it
    is is unknown,
    so its view is the newest frame moved by the events since (the model from the trajectory's clamped
    end would draw another view); a pose given is still the model's, and a still camera's view too."""
    rec, model = long_scene
    assert not model.meta.trajectory.is_static
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    kept = AnchorStore(64)  # a cold start's: its model learnt from the stream's frames
    engine = Engine(Timebase(model, online, kept), ring, cache_size=4)
    start = rec.t_range_us[0]
    engine.timeline = tl = Timeline(start, start)
    head = model.meta.t_end_us + 5 * STEP_US + 20_000
    ring.push(rec.events.time_slice(start, head + 1), complete_until_us=head + 1)
    sel = rec.anchors.t_us <= head
    kept.add_frames(Frames(rec.anchors.t_us[sel], rec.anchors.images[sel]))
    online.on_frames(Frames(rec.anchors.t_us[sel], rec.anchors.images[sel]), tl.scene_of)
    out = engine.render(None, None, 64, 48)
    anchor = online.anchors()[-1]
    assert out.anchor == "frame" and out.model_version is None and out.instant.anchor_us == anchor.t_us
    emap = accumulate(ring.slice(*out.instant.window), 64, 48)
    assert np.abs(emap).sum() > 0
    want = integrate(anchor.frame, emap, model.config.contrast_threshold, eps=model.config.log_eps)
    assert np.abs(out.pixels.astype(int) - np.rint(np.clip(want, 0, 1) * 255).astype(int)).max() <= 1
    pose = model.meta.trajectory.at(out.instant.t_us)
    assert engine.render(None, pose, 64, 48, camera_view=False).anchor == "predicted"
    # within the span, and a camera that stood still: the model's view, projected
    assert engine.render(model.meta.t_end_us - 10_000, None, 64, 48).anchor == "checkpoint"
    still = copy.deepcopy(model)
    still.meta.trajectory = Trajectory(still.meta.trajectory.t_us[:1], still.meta.trajectory.c2w[:1])
    engine.swap(Timebase(still, online, kept))
    assert engine.render(None, None, 64, 48).anchor == "predicted"
    # a checkpoint given (no frames kept) draws from its trajectory's end past its span
    engine.swap(Timebase(model, online))
    assert engine.render(None, None, 64, 48).anchor == "predicted"


REAL = {"anchor_windows": True, "bg_layer": True, "dynamic_threshold": 0.06}  # the real preset's switches


@pytest.fixture(scope="module")
def windowed_scene(tmp_path_factory):
    """The long scene's recording with a checkpoint drawn in anchor windows over a background layer."""
    rec_path, ckpt = build_scene(tmp_path_factory.mktemp("online_windows"), width=64, height=48,
                                 duration_s=1.5, anchor_every_s=0.1, frames_per_anchor=2, event_rate=20_000,
                                 init_points=1000, control_points=32, event_branch_seed=0, train_s=0.5,
                                 config_overrides=REAL)
    from edmcgs.sensor.files.recording import read_recording

    model = load_checkpoint(ckpt)
    assert model.gaussians.birth is not None and model.bg_layer is not None
    return read_recording(rec_path), model, rec_path, ckpt


def test_online_anchors_of_a_windowed_checkpoint_carry_its_last_window_forward(windowed_scene):
    rec, model, *_ = windowed_scene
    last = len(model.meta.anchors_us) - 1
    t = int(model.meta.t_end_us) + STEP_US
    # without events the prediction is the checkpoint's own state past its span (deform's rule there)
    ours = model_online.state_of(model, model_online.checkpoint_motion(model, t))
    theirs = model.deform(t)  # the last window's Gaussians alone
    drawn = ours.opacities > 0
    assert bool(drawn.any()) and torch.equal(drawn, model.gaussians.birth == last)
    torch.testing.assert_close(ours.means[drawn], theirs.means, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(ours.opacities[drawn], theirs.opacities)
    # the fit composites the background layer behind the last window's Gaussians, and lowers the loss
    i = int(np.searchsorted(rec.anchors.t_us, t))
    (trans, _), colors, first, after = model_online.correct(model, model_online.checkpoint_motion(model, t),
                                                    rec.anchors.images[i], rec.anchors.poses[i],
                                                    model.meta.intrinsics, steps=6, lr=6e-3)
    assert np.isfinite(first) and after < first and bool(torch.isfinite(trans).all()) and colors is None
    moved = ~(model.gaussians.birth == last)
    fitted = model_online.state_of(model, (trans, model_online.checkpoint_motion(model, t)[1]))
    assert float(fitted.opacities[moved].abs().max()) == 0.0  # other windows stay undrawn


def test_spawned_gaussians_draw_what_the_frame_shows_that_the_render_lacks(windowed_scene):
    rec, model, *_ = windowed_scene
    t = int(model.meta.t_end_us) + STEP_US
    i = int(np.searchsorted(rec.anchors.t_us, t))
    c2w, intr = rec.anchors.poses[i], model.meta.intrinsics
    state = model_online.state_of(model, model_online.checkpoint_motion(model, t))
    rendered = np.round(model.render(state, c2w, intr) * 255).astype(np.uint8)
    assert model_online.spawn(model, state, rendered, c2w, intr, limit=100) is None  # nothing lacking
    frame = rendered.copy()
    frame[10:30, 20:44] = [250, 20, 20]  # something new entered the view
    spawned = model_online.spawn(model, state, frame, c2w, intr, limit=100)
    assert spawned is not None and 0 < len(spawned) <= 100
    assert bool(torch.isfinite(spawned.means).all()) and bool((spawned.scales > 0).all())
    patch = (slice(10, 30), slice(20, 44))
    before = np.abs(rendered[patch].astype(float) - frame[patch]).mean()
    with_new = model.render(model_online.with_spawned(state, spawned), c2w, intr) * 255
    assert np.abs(with_new[patch] - frame[patch]).mean() < 0.5 * before
    assert model_online.spawn(model, state, frame, c2w, intr, limit=0) is None


def test_a_corrected_anchor_of_a_windowed_checkpoint_carries_its_spawned_gaussians_on(windowed_scene):
    rec, model, *_ = windowed_scene
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False, fit_steps=2, fit_scale=1.0, colour_lr=0.0,
                                                    spawn=50))
    start = rec.t_range_us[0]
    tl = Timeline(start, start)
    first = int(model.meta.t_end_us) + STEP_US
    _feed(online, ring, rec, first + 1, tl)
    a = online.anchors()[-1]
    online._fit(a, rec.anchors.images[int(np.searchsorted(rec.anchors.t_us, a.stream_us))])
    fitted = online.anchors()[-1]
    assert fitted.corrected and fitted.spawned is not None and len(fitted.spawned) <= 50
    _feed(online, ring, rec, first + STEP_US + 1, tl, from_us=first + 1)
    assert online.anchors()[-1].spawned is fitted.spawned  # the prediction inherits them
    plain = OnlineAnchors(model, ring, OnlineConfig(fit=False, spawn=0))
    assert plain.spawn_limit == 0


def test_a_windowed_checkpoint_renders_past_its_span_from_online_anchors(windowed_scene):
    from edmcgs.server import service as service_module
    from edmcgs.server.settings import Settings

    rec, model, rec_path, ckpt = windowed_scene
    service = service_module.Service.open(Settings(replay=rec_path, checkpoint=ckpt))
    try:
        assert service.online is not None
    finally:
        service.close()
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False))
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    start = rec.t_range_us[0]
    engine.timeline = tl = Timeline(start, start)
    head = model.meta.t_end_us + 4 * STEP_US + 20_000
    _feed(online, ring, rec, head + 1, tl)
    assert len(online.anchors()) == 4
    out = engine.render(None, None, 64, 48)
    assert out.anchor == "predicted" and out.instant.anchor_us == online.anchors()[-1].t_us
    frame = rec.anchors.images[int(np.searchsorted(rec.anchors.t_us, online.anchors()[-1].t_us))]
    # the background layer is drawn behind: the render is close to the frame, not the flat colour
    assert np.abs(out.pixels.astype(np.float64) - frame).mean() < 40


def test_a_correction_equals_refitting_through_the_full_skinning(long_scene):
    # correct() skins once and adds the blended residual per step (skinning is linear in translations):
    # the same fit as re-skinning the whole state at every step.
    from edmcgs.geometry import world_to_camera
    from edmcgs.model.dynamic import background_color, render_image

    rec, model = long_scene
    t = int(model.meta.t_end_us) + STEP_US
    motion = model_online.checkpoint_motion(model, t)
    i = int(np.searchsorted(rec.anchors.t_us, t))
    image, c2w, intr = rec.anchors.images[i], rec.anchors.poses[i], model.meta.intrinsics
    (got, _), _, first, last = model_online.correct(model, motion, image, c2w, intr, steps=4, lr=2e-3)

    trans0, rot = motion
    target = torch.as_tensor(image, dtype=torch.float32) / 255.0
    w2c = torch.as_tensor(world_to_camera(np.asarray(c2w, np.float64)), dtype=torch.float32)
    bg, extent = background_color(model.config, model.meta.channels), float(model.extent)
    delta = torch.zeros_like(trans0, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=2e-3)
    losses = []
    for _ in range(4):
        state = model.state_from_motion(trans0 + delta * extent, rot)
        loss = (render_image(state, w2c, intr, bg) - target).abs().mean()
        losses.append(float(loss.detach()))
        opt.zero_grad()
        (loss + 1e-2 * delta.pow(2).sum(-1).mean()).backward()
        opt.step()
    assert first == pytest.approx(losses[0], rel=1e-5) and last == pytest.approx(losses[-1], rel=1e-4)
    assert torch.allclose(got, trans0 + delta.detach() * extent, atol=1e-6 * extent)
    assert last < first  # the fit moves toward the frame


def test_fine_tuning_g_phi_learns_from_corrections_and_touches_only_the_span_past_the_checkpoint(long_scene):
    rec, model = long_scene
    own = [p.detach().clone() for p in model.transition.parameters()]
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False, fit_steps=3, fit_scale=0.5, colour_lr=0.0,
                                                    finetune_steps=4, finetune_lr=1e-3, transition="g_phi"))
    start = rec.t_range_us[0]
    tl = Timeline(start, start)
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    engine.timeline = tl
    _feed(online, ring, rec, int(model.meta.t_end_us) + 3 * STEP_US + 1, tl)
    inside = int(model.meta.anchors_us[1]) + STEP_US // 2
    before = engine.render(inside, None, 64, 48).pixels
    first, second = online.anchors()[:2]
    online._fit(first, rec.anchors.images[int(np.searchsorted(rec.anchors.t_us, first.stream_us))])
    assert online.transitions.module is not model.transition and online.transitions.version == 1
    tuned_once = online.transitions.module
    online._fit(second, rec.anchors.images[int(np.searchsorted(rec.anchors.t_us, second.stream_us))])
    assert online.transitions.module is not tuned_once and online.transitions.version == 2
    loss_before, loss_after = online.last_finetune
    assert np.isfinite(loss_before) and loss_after < loss_before  # it learns the correction
    assert all(torch.equal(p, q) for p, q in zip(own, model.transition.parameters(), strict=True))
    assert not any(p.requires_grad for p in online.transitions.module.parameters())
    # the checkpoint's span renders exactly as before; past it the new transition drives the motion
    assert np.array_equal(engine.render(inside, None, 64, 48).pixels, before)
    later = int(second.stream_us) + STEP_US // 2
    tuned = engine.render(later, None, 64, 48).pixels
    online.transitions.module, online.transitions.version = model.transition, 0
    assert not np.array_equal(engine.render(later, None, 64, 48).pixels, tuned)


def test_the_transition_past_the_span_is_the_one_that_predicted_the_recent_frames_best(long_scene):
    rec, model = long_scene
    ring = EventRingBuffer(10**6)
    # the model's render alone (no projection onto the events): what the transition moves
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False, fit_steps=1, fit_scale=0.5, colour_lr=0.0,
                                                    project=False))
    moves = online.transitions
    assert moves.select and moves.kind == "g_phi" and list(moves.evidence) == ["g_phi", "none"]
    start, end = rec.t_range_us[0], int(model.meta.t_end_us)
    tl = Timeline(start, start)
    # a scene that stops at the span's end while its events go on: every frame past it shows the state
    # the checkpoint ends in, so standing still predicts each one best
    until, horizon = end + 3 * STEP_US + 1, end + 4 * STEP_US
    ring.push(rec.events.time_slice(start, horizon), complete_until_us=horizon)
    sel = (rec.anchors.t_us > end) & (rec.anchors.t_us < until)
    still = model_online.state_of(model, model_online.checkpoint_motion(model, end))
    images = np.stack([np.round(model.render(still, pose, model.meta.intrinsics) * 255).astype(np.uint8)
                       for pose in rec.anchors.poses[sel]])
    online.on_frames(Frames(rec.anchors.t_us[sel], images, rec.anchors.poses[sel]), tl.scene_of)
    for anchor, image in zip(online.anchors(), images, strict=True):
        online._fit(anchor, image)
    assert all(len(v) == 3 for v in online.transitions.evidence.values())
    assert np.mean(moves.evidence["none"]) < np.mean(moves.evidence["g_phi"])
    assert moves.kind == "none" and moves.module is None and moves.version == 1
    # from now on a render past the span holds its anchor's state, whatever the events since
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    engine.timeline = tl
    last = online.anchors()[-1]
    assert len(ring.slice(last.stream_us, horizon - 1)) > 0
    held = engine.render(last.stream_us, None, 64, 48).pixels
    assert np.array_equal(engine.render(horizon - 1, None, 64, 48).pixels, held)


def test_finetune_without_events_has_nothing_to_learn(long_scene):
    _, model = long_scene
    motion = model_online.checkpoint_motion(model, int(model.meta.t_end_us))
    assert model_online.finetune(model, model.transition, motion, None, None, motion[0], steps=3,
                                 lr=1e-3) is None
    empty = np.zeros((model.meta.event_height, model.meta.event_width), np.float32)
    assert model_online.finetune(model, model.transition, motion, empty, None, motion[0], steps=3,
                                 lr=1e-3) is None


@pytest.mark.parametrize("flag", ["--online-spawn", "--online-finetune-steps"])
def test_the_serve_flags_of_the_online_switches_are_checked(flag, capsys):
    from edmcgs.server.cli import main

    assert main([flag, "-1"]) == 2
    assert flag.lstrip("-").replace("-", "_") in capsys.readouterr().err


def test_colour_offsets_learn_what_the_frame_shows_and_stay_put_without_a_step_size(long_scene):
    rec, model = long_scene
    t = int(model.meta.t_end_us) + STEP_US
    i = int(np.searchsorted(rec.anchors.t_us, t))
    c2w, intr = rec.anchors.poses[i], model.meta.intrinsics
    motion = model_online.checkpoint_motion(model, t)
    rendered = np.round(model.render(model_online.state_of(model, motion), c2w, intr) * 255).astype(np.uint8)
    frame = rendered.copy()
    patch = (slice(12, 36), slice(16, 48))
    frame[patch] = np.clip(frame[patch].astype(int) + np.array([60, -40, 30]), 0, 255)  # never seen
    before = np.abs(rendered[patch].astype(float) - frame[patch]).mean()
    motion2, colors, first, last = model_online.correct(model, motion, frame, c2w, intr, steps=12, lr=1e-3,
                                                        colour_lr=0.05)
    assert colors is not None and colors.shape == (len(model.gaussians), model.meta.channels)
    assert bool(torch.isfinite(colors).all()) and last < first
    after = model.render(model_online.state_of(model, motion2, colors), c2w, intr) * 255
    assert np.abs(after[patch] - frame[patch]).mean() < 0.6 * before
    # without a step size the offsets pass through unchanged (and none stay none)
    _, same, _, _ = model_online.correct(model, motion, frame, c2w, intr, steps=3, colors=colors)
    assert same is colors
    assert model_online.correct(model, motion, frame, c2w, intr, steps=3)[1] is None
    # SH colours take the offset on their base colour (the DC term)
    sh = torch.zeros(len(colors), 4, colors.shape[1])
    moved = model_online.recolored(sh, colors)
    torch.testing.assert_close(moved[:, 0] * SH_C0, colors)
    assert float(moved[:, 1:].abs().max()) == 0.0


def test_corrections_learn_colours_that_carry_to_the_next_anchors(long_scene):
    rec, model = long_scene
    ring = EventRingBuffer(10**6)
    online = OnlineAnchors(model, ring, OnlineConfig(fit=False, fit_steps=3, fit_scale=1.0, colour_lr=0.02))
    tl = Timeline(rec.t_range_us[0], rec.t_range_us[0])
    _feed(online, ring, rec, model.meta.t_end_us + STEP_US + 1, tl)
    first = online.anchors()[0]
    assert first.colors is None  # nothing learnt before the first correction
    online._fit(first, rec.anchors.images[rec.anchors.t_us == first.t_us][0])
    fitted = online.anchors()[0]
    assert fitted.corrected and fitted.colors is not None and bool(fitted.colors.abs().sum() > 0)
    end = model.meta.t_end_us
    _feed(online, ring, rec, end + 2 * STEP_US + 1, tl, from_us=end + STEP_US + 1)
    nxt = online.anchors()[1]
    assert not nxt.corrected and nxt.colors is fitted.colors  # the prediction inherits them
    # and the served render past that anchor draws them
    engine = Engine(Timebase(model, online), ring, cache_size=4)
    engine.timeline = tl
    instant = engine.resolve(nxt.t_us)
    state, _ = engine.state(instant)
    torch.testing.assert_close(state.colors, model_online.state_of(model, nxt.motion).colors + fitted.colors)
