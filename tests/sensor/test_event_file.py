"""A recording's events read from its file a window at a time (``FileEvents``) equal the whole read."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from edmcgs.pipeline import cut, open_recording, training_data
from edmcgs.sensor.events import Events
from edmcgs.sensor.files import event_file
from edmcgs.sensor.files.event_file import FileEvents
from edmcgs.sensor.files.recording import Recording, read_recording, write_recording
from edmcgs.sensor.frames import Frames


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A recording of 60k events over 60 ms, 300 of them at one time."""
    rng = np.random.default_rng(0)
    n, width, height = 60_000, 64, 48
    t = 1_700_000_000_000_000 + np.sort(rng.integers(0, 60_000, n))
    t[1000:1300] = t[1000]  # a run of equal times across a coarse-index entry
    events = Events(t, rng.integers(0, width, n), rng.integers(0, height, n), rng.choice([-1, 1], n))
    t_a = np.linspace(t[0], t[-1], 5).astype(np.int64)
    rec = Recording(width=width, height=height, events=events,
                    anchors=Frames(t_a, rng.integers(0, 256, (5, height, width, 1), dtype=np.uint8)))
    path = tmp_path_factory.mktemp("event_file") / "rec.h5"
    write_recording(path, rec)
    return path, rec


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    # Blocks and index entries of a few hundred events: every read crosses their boundaries.
    monkeypatch.setattr(event_file, "STRIDE", 64)
    monkeypatch.setattr(event_file, "BLOCK_EVENTS", 500)


def same(a: Events, b: Events) -> bool:
    return all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "txyp")


def test_windows_read_from_the_file_equal_the_whole_recording_read(written):
    path, rec = written
    lazy = read_recording(path, lazy_events=True)
    assert isinstance(lazy.events, FileEvents) and len(lazy.events) == len(rec.events)
    assert (lazy.events.t_start, lazy.events.t_end) == (rec.events.t_start, rec.events.t_end)
    assert same(lazy.events.read(), rec.events)
    rng = np.random.default_rng(3)
    lo, hi = int(rec.events.t[0]) - 50, int(rec.events.t[-1]) + 50
    edges = [int(rec.events.t[1000]), int(rec.events.t[1000]) + 1]  # at and just past the run of equal times
    starts = np.concatenate([rng.integers(lo, hi, 150), edges]).tolist()
    for t0 in starts:  # random windows, in random order (blocks reused and replaced)
        t1 = t0 + int(rng.integers(0, 40_000))
        assert same(lazy.events.read(t0, t1), rec.events.time_slice(t0, t1)), (t0, t1)
    t0 = int(rec.events.t[20_000])
    for k in range(30):  # consecutive windows, as a gap's sub-steps ask
        a, b = t0 + 997 * k, t0 + 997 * (k + 1)
        assert same(lazy.events.read(a, b), rec.events.time_slice(a, b))


def test_a_view_cuts_and_slices_as_events_do(written):
    path, rec = written
    lazy = read_recording(path, lazy_events=True).events
    t0, t1 = int(rec.events.t[5_000]), int(rec.events.t[41_000])
    view, whole = lazy.time_slice(t0, t1), rec.events.time_slice(t0, t1)
    assert len(view) == len(whole) and (view.t_start, view.t_end) == (whole.t_start, whole.t_end)
    assert same(view.read(), whole) and same(view[100:2100], whole[100:2100])
    # a window reaching outside the view reads only the view's events
    assert same(view.read(t0 - 10_000, t0 + 5_000), whole.time_slice(t0 - 10_000, t0 + 5_000))
    assert len(lazy.time_slice(t1, t0)) == 0 and len(view.read(t1 + 1, t1 + 100)) == 0


def test_a_lazy_recording_trains_on_the_same_event_maps(written):
    path, _ = written
    lazy = open_recording(path, lazy_events=True, start_s=0.004, duration_s=0.03)
    whole = cut(read_recording(path), start_s=0.004, duration_s=0.03)
    assert isinstance(lazy.events, FileEvents) and same(lazy.events.read(), whole.events)
    a, b = training_data(lazy), training_data(whole)
    assert a.t_end_us == b.t_end_us
    times = np.linspace(a.anchors_t_us[0], a.t_end_us, 9).astype(np.int64)
    for t0, t1 in itertools.pairwise(times):
        np.testing.assert_array_equal(a.event_map(int(t0), int(t1)), b.event_map(int(t0), int(t1)))
