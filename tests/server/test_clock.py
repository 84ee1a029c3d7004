"""The server's clock algebra on its own: timelines, resolving a time to an instant, what is renderable."""

from __future__ import annotations

import numpy as np
import pytest

from edmcgs.protocol import TauSource
from edmcgs.server.live.clock import (
    Span,
    TauRule,
    Timeline,
    TimeNotRenderable,
    instant,
    locate,
    playback_watermark,
    renderable,
)

T0 = 1_600_000_000_000_000
ANCHORS = np.array([T0, T0 + 100_000, T0 + 200_000], dtype=np.int64)
SPAN = Span(T0, T0 + 250_000)


def resolve(t_us, head, timeline, span, tau_of):
    """locate, then the instant from the anchor ``tau_of`` gives (as the engine's timebase does)."""
    query = locate(t_us, head, timeline, span, T0)
    return instant(query, tau_of(query.stream_t, query.t_us), timeline, span, T0)


def tau(stream_t, scene_t):
    """tau on the stream clock from the scene's anchors."""
    i = int(np.searchsorted(ANCHORS, scene_t, side="right")) - 1
    return None if i < 0 else stream_t - (scene_t - int(ANCHORS[i]))


def test_timeline_without_loop_is_an_offset():
    tl = Timeline(stream_origin_us=T0, scene_origin_us=5, period_us=None)
    assert tl.scene_of(T0 + 7) == 12
    assert tl.stream_of(12, not_after_us=T0) == T0 + 7  # may lie beyond the head; the caller checks
    assert tl.pass_start(T0 + 7) is None


def test_timeline_loops_and_picks_the_latest_pass():
    period = 2_000_001
    tl = Timeline(T0, T0, period)
    assert tl.scene_of(T0 + period + 10) == T0 + 10
    assert tl.scene_of(T0 + 3 * period - 1) == T0 + period - 1
    assert tl.pass_start(T0 + 2 * period + 5) == T0 + 2 * period
    head = T0 + 2 * period + 500_000
    assert tl.stream_of(T0 + 400_000, head) == T0 + 2 * period + 400_000
    assert tl.stream_of(T0 + 600_000, head) == T0 + period + 600_000  # not reached in this pass yet
    assert tl.stream_of(T0 + 600_000, T0 + 100) < T0  # not streamed at all yet
    for stream_t in (T0, T0 + 1, head, T0 + 7 * period - 1):
        assert tl.stream_of(tl.scene_of(stream_t), stream_t) == stream_t
    with pytest.raises(ValueError):
        Timeline(T0, T0, 0)


def test_resolve_gives_the_anchor_and_the_half_open_window():
    tl = Timeline(T0, T0)
    inst = resolve(T0 + 150_000, T0 + 250_000, tl, SPAN, tau)
    assert (inst.t_us, inst.anchor_us) == (T0 + 150_000, T0 + 100_000)
    assert inst.window == (T0 + 100_000, T0 + 150_000)
    head = resolve(None, T0 + 120_000, tl, SPAN, tau)
    assert head.t_us == T0 + 120_000 and head.anchor_us == T0 + 100_000


def test_resolve_says_why_a_time_cannot_be_rendered():
    tl = Timeline(T0, T0)
    with pytest.raises(TimeNotRenderable, match="outside the checkpoint's span"):
        resolve(T0 + 300_000, T0 + 250_000, tl, SPAN, tau)
    with pytest.raises(TimeNotRenderable, match="not been streamed yet"):
        resolve(T0 + 150_000, T0 + 120_000, tl, SPAN, tau)
    with pytest.raises(TimeNotRenderable, match="no anchor frame"):
        resolve(T0 + 50_000, T0 + 120_000, tl, SPAN, lambda stream_t, scene_t: None)


def test_tau_comes_from_the_checkpoint_over_its_span_whatever_frames_the_stream_has():
    for frames in (False, True):
        rule = TauRule(SPAN, stream_frames=frames)
        for t in (T0, T0 + 230_000, SPAN.end_us):
            assert rule.source(t) is TauSource.CHECKPOINT
        assert rule.ranges() == [(TauSource.CHECKPOINT, T0, SPAN.end_us)]
        # where the checkpoint has no anchor, only the stream's frames could give one
        assert rule.source(SPAN.end_us + 1) is (TauSource.STREAM if frames else None)
        assert rule.source(T0 - 1) is (TauSource.STREAM if frames else None)


def test_a_window_never_reaches_back_into_the_previous_pass_of_a_loop():
    """A recording starting after the checkpoint's first anchor: on a looping pass, times whose anchor
    precedes the pass start have no complete window (it would hold the end of the previous pass)."""
    start = T0 + 40_000  # the file begins 40 ms after the first anchor
    period = SPAN.end_us + 1 - start
    tl = Timeline(start, start, period)
    head = start + period + 200_000  # second pass
    with pytest.raises(TimeNotRenderable, match="precedes the start of the looping stream's pass"):
        resolve(T0 + 60_000, head, tl, SPAN, tau)
    inst = resolve(T0 + 150_000, head, tl, SPAN, tau)
    assert inst.window == (T0 + period + 100_000, T0 + period + 150_000)
    # a whole earlier pass retained: renderable from the first anchor inside a pass
    assert renderable(start + 2 * period + 10, tl, SPAN, ANCHORS, start, dropped=False) == [
        (T0 + 100_000, SPAN.end_us)]


def test_renderable_without_a_loop_runs_from_the_first_retained_anchor_to_the_head():
    tl = Timeline(T0, T0)
    assert renderable(T0 + 150_000, tl, SPAN, ANCHORS, T0, dropped=False) == [(T0, T0 + 150_000)]
    # events before T0 + 50 ms were dropped: the first complete window starts at the next anchor
    assert renderable(T0 + 150_000, tl, SPAN, ANCHORS, T0 + 50_000, dropped=True) == [(T0 + 100_000,
                                                                                       T0 + 150_000)]
    assert renderable(T0 + 150_000, tl, SPAN, ANCHORS, None, dropped=True) == []


def test_renderable_with_a_loop_joins_the_previous_pass():
    period = 250_001
    tl = Timeline(T0, T0, period)
    head = T0 + period + 50_000  # second pass, 50 ms in
    assert renderable(head, tl, SPAN, ANCHORS, T0, dropped=False) == [(T0, SPAN.end_us)]
    # only the end of the first pass retained: its last anchor on, then the second pass up to the head
    got = renderable(head, tl, SPAN, ANCHORS, T0 + 120_000, dropped=True)
    assert got == [(T0 + 200_000, SPAN.end_us), (T0, T0 + 50_000)]
    # two whole passes behind the head: the whole span
    assert renderable(T0 + 2 * period + 10, tl, SPAN, ANCHORS, T0, dropped=False) == [(T0, SPAN.end_us)]


def test_playback_starts_two_passes_in_and_runs_at_its_speed():
    period = 1_000_001
    assert playback_watermark(T0, period, 0, 1.0) - 1 == T0 + 2 * period
    assert Timeline(T0, T0, period).scene_of(playback_watermark(T0, period, 0, 1.0) - 1) == T0
    assert playback_watermark(T0, period, 1000, 2.0) == playback_watermark(T0, period, 0, 1.0) + 2000
