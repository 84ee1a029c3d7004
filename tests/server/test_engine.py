"""The engine's time resolution on a real checkpoint and ring: what can be rendered, and why not."""

from __future__ import annotations

import numpy as np
import pytest

from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import read_recording
from edmcgs.server.engine import Engine
from edmcgs.server.live.clock import Timeline, TimeNotRenderable


@pytest.fixture(scope="module")
def scene(scene_files):
    rec, ckpt = scene_files
    return read_recording(rec), load_checkpoint(ckpt)


def _engine(scene, capacity: int, loop: bool) -> tuple[Engine, Events]:
    rec, model = scene
    events = rec.events
    start, end = rec.t_range_us
    engine = Engine(model, EventRingBuffer(capacity), cache_size=4)
    engine.timeline = Timeline(start, start, end + 1 - start if loop else None)
    return engine, events


def test_everything_streamed_so_far_is_renderable(scene):
    engine, events = _engine(scene, capacity=10**6, loop=False)
    t0 = engine.first_us
    engine.ring.push(events.time_slice(t0, t0 + 600_000), complete_until_us=t0 + 600_000)
    assert engine.renderable() == [(t0, t0 + 599_999)]  # the watermark is exclusive
    inst = engine.resolve(t0 + 400_000)
    assert inst.anchor_us == t0 + 250_000 and inst.window == (t0 + 250_000, t0 + 400_000)
    assert engine.resolve(None).t_us == t0 + 599_999  # the head
    with pytest.raises(TimeNotRenderable, match="not been streamed yet") as info:
        engine.resolve(t0 + 700_000)
    assert info.value.valid_range["t_us_max"] == t0 + 599_999
    with pytest.raises(TimeNotRenderable, match="outside the checkpoint's span"):
        engine.resolve(t0 - 1)


def test_after_overflow_the_range_starts_at_the_first_anchor_still_covered(scene):
    engine, events = _engine(scene, capacity=15_000, loop=False)  # ~0.75 s of 20k ev/s
    t0 = engine.first_us
    engine.ring.push(events.time_slice(t0, t0 + 1_500_000), complete_until_us=t0 + 1_500_000)
    oldest = engine.ring.oldest_us
    (lo, hi), = engine.renderable()
    assert hi == t0 + 1_499_999 and lo > oldest and (lo - t0) % 250_000 == 0 and lo - 250_000 <= oldest
    with pytest.raises(TimeNotRenderable, match="renderable now"):
        engine.state(engine.resolve(lo - 1))  # its anchor's events were dropped
    _, n = engine.state(engine.resolve(lo + 100_000))
    assert n == len(events.time_slice(lo, lo + 100_000))


def test_a_loop_maps_every_pass_onto_the_scene(scene):
    engine, events = _engine(scene, capacity=10**6, loop=True)
    t0 = engine.first_us
    period = engine.timeline.period_us
    second = events.time_slice(t0, t0 + 500_000).shifted(period)
    engine.ring.push(events, complete_until_us=t0 + period)
    engine.ring.push(second, complete_until_us=t0 + period + 500_000)
    assert engine.renderable() == [(t0, engine.end_us)]  # a whole pass is retained
    inst = engine.resolve(t0 + 300_000)
    assert inst.window == (t0 + period + 250_000, t0 + period + 300_000)  # the latest pass
    inst = engine.resolve(t0 + 900_000)
    assert inst.window == (t0 + 750_000, t0 + 900_000)  # not reached again yet: the previous pass
    _, n = engine.state(inst)
    assert n == len(events.time_slice(t0 + 750_000, t0 + 900_000))
    head = engine.resolve(None)
    assert head.t_us == t0 + 499_999 and head.anchor_us == t0 + 250_000


def test_nothing_renderable_before_events(scene):
    engine, _ = _engine(scene, capacity=100, loop=False)
    assert engine.renderable() == [] and engine.head() is None
    with pytest.raises(TimeNotRenderable, match="no events have arrived") as info:
        engine.resolve(None)
    assert info.value.valid_range is None
    assert np.isfinite(engine.seconds_of(engine.first_us))


def test_at_a_pass_boundary_the_first_anchor_comes_from_the_pass_that_has_it(scene):
    """The ring is complete up to the end of pass 1, whose next anchor (pass 2's first) has not arrived:
    t = the first anchor must be served from pass 1, not fail for want of pass 2's frame."""
    rec, _ = scene
    engine, events = _engine(scene, capacity=10**6, loop=True)
    engine.anchors = AnchorStore(16)
    engine.anchors.add_frames(rec.anchors)
    t0, period = engine.first_us, engine.timeline.period_us
    engine.ring.push(events, complete_until_us=t0 + period)
    inst = engine.resolve(t0)
    assert inst.window == (t0, t0) and inst.anchor_us == t0
    assert engine.resolve(None).t_us == engine.end_us
