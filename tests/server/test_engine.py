"""The engine's time resolution on a real checkpoint and ring: what can be rendered, and why not."""

from __future__ import annotations

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import read_recording
from edmcgs.server.engine import Engine
from edmcgs.server.live.clock import Timeline, TimeNotRenderable
from edmcgs.server.live.timebase import Timebase


@pytest.fixture(scope="module")
def scene(scene_files):
    rec, ckpt = scene_files
    return read_recording(rec), load_checkpoint(ckpt)


def _engine(scene, capacity: int, loop: bool) -> tuple[Engine, Events]:
    rec, model = scene
    events = rec.events
    start, end = rec.t_range_us
    engine = Engine(Timebase(model), EventRingBuffer(capacity), cache_size=4)
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
    engine, events = _engine(scene, capacity=10**6, loop=True)
    t0, period = engine.first_us, engine.timeline.period_us
    engine.ring.push(events, complete_until_us=t0 + period)
    inst = engine.resolve(t0)
    assert inst.window == (t0, t0) and inst.anchor_us == t0
    assert engine.resolve(None).t_us == engine.end_us


def test_depth_and_alpha_modes_are_the_reference_renderers(scene):
    """A depth render decodes (near, far from its range) to the float64 reference renderer's expected
    depth, sum w_i z_i / sum w_i, within a grey step; an alpha render is its 1 - T; both grey, the splats'
    alone."""
    from edmcgs import protocol
    from edmcgs.clients.client import depth_metres
    from edmcgs.geometry import world_to_camera
    from edmcgs.model.render import reference

    engine, events = _engine(scene, capacity=10**6, loop=False)
    t0 = engine.first_us
    engine.ring.push(events.time_slice(t0, t0 + 600_000), complete_until_us=t0 + 600_000)
    t = t0 + 400_000
    pose = np.array([[0.995, 0.0, 0.0998, 0.05], [0.0, 1.0, 0.0, 0.0], [-0.0998, 0.0, 0.995, 0.0],
                     [0.0, 0.0, 0.0, 1.0]])  # 5 cm to the right, turned ~6 degrees: not the camera's view
    width, height = 80, 60
    state, _ = engine.state(engine.resolve(t))
    arrays = [a.detach().numpy() for a in state.tensors()]
    _, ref_alpha, ref_depth = reference.render_camera(arrays, world_to_camera(pose),
                                                      engine.intrinsics(width, height))

    alpha = engine.render(t, pose, width, height, mode="alpha")
    assert alpha.pixels.shape == (height, width, 1) and alpha.mode == "alpha" and alpha.depth_range is None
    np.testing.assert_allclose(alpha.pixels[..., 0], ref_alpha * 255, atol=0.51 + 255e-4)
    assert 0.2 < ref_alpha.mean() < 0.99  # covered in places, open in others

    depth = engine.render(t, pose, width, height, mode="depth")
    assert depth.pixels.shape == (height, width, 1) and depth.mode == "depth" and not depth.projected
    near, far = depth.depth_range
    covered = ref_alpha >= protocol.DEPTH_MIN_ALPHA
    np.testing.assert_allclose((near, far), np.percentile(ref_depth[covered], (1, 99)), rtol=1e-3)
    meta = protocol.FrameMeta(t, 0.0, t0, 0, 0.0, width, height, 1, "raw", "checkpoint", False,
                              render_mode="depth", depth_near=near, depth_far=far)
    z = depth_metres(depth.pixels, meta)
    clear = np.abs(ref_alpha - protocol.DEPTH_MIN_ALPHA) > 1e-3  # off the threshold's float32 rounding
    assert np.isnan(z[clear & ~covered]).all() and not np.isnan(z[clear & covered]).any()
    step = (far - near) / 254
    np.testing.assert_allclose(z[clear & covered], np.clip(ref_depth, near, far)[clear & covered],
                               atol=0.5 * step + 1e-4 * far)
    inside = clear & covered & (ref_depth > near) & (ref_depth < far)
    assert inside.mean() > 0.15 and np.ptp(z[inside]) > 50 * step  # a range of depths, not one grey

    rgb = engine.render(t, pose, width, height)
    assert rgb.mode == "rgb" and rgb.pixels.shape == (height, width, 3) and rgb.depth_range is None
    with pytest.raises(InvalidInputError, match="mode must be one of rgb, depth, alpha"):
        engine.render(t, pose, width, height, mode="normals")
