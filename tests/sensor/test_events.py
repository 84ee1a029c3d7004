import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.events import DEFAULT_MAX_DISORDER_US, Events, EventStats, normalize_polarity


def _ev(t, x=None, y=None, p=None):
    n = len(t)
    return Events(np.asarray(t, np.int64), np.zeros(n, np.uint16) if x is None else x,
                  np.zeros(n, np.uint16) if y is None else y, np.ones(n, np.int8) if p is None else p)


def test_strict_constructor_converts_value_preserving_dtypes():
    ev = Events([1, 2, 3], np.array([0, 5, 7], np.int32), [1, 2, 3], np.array([1, -1, 1], np.int64))
    assert ev.t.dtype == np.int64 and ev.x.dtype == np.uint16 and ev.y.dtype == np.uint16
    assert ev.p.dtype == np.int8 and ev.p.tolist() == [1, -1, 1]


@pytest.mark.parametrize("kwargs, match", [
    ({"p": [1, 0, 1]}, "must be \\+1 or -1"),
    ({"t": [3, 2, 1]}, "goes backwards at index 1"),
    ({"t": [1.0, 2.0, 3.0]}, "integer microseconds"),
    ({"x": [0, -1, 2]}, "outside \\[0, 65535\\]"),
    ({"y": [0, 1]}, "equal length"),
    ({"x": np.zeros((3, 1))}, "1-D"),
])
def test_strict_constructor_rejects(kwargs, match):
    cols = {"t": [1, 2, 3], "x": [0, 1, 2], "y": [0, 1, 2], "p": [1, -1, 1]} | kwargs
    with pytest.raises(InvalidInputError, match=match):
        Events(**cols)


@pytest.mark.parametrize("raw, want", [
    (np.array([0, 1, 1, 0], np.uint8), [-1, 1, 1, -1]),
    (np.array([False, True, True, False]), [-1, 1, 1, -1]),
    (np.array([-1, 1, 1, -1], np.int64), [-1, 1, 1, -1]),
    (np.array([0.0, 1.0, 1.0, 0.0]), [-1, 1, 1, -1]),
    (np.array([1, 1, 1, 1], np.uint32), [1, 1, 1, 1]),
])
def test_polarity_conventions(raw, want):
    assert normalize_polarity(raw).tolist() == want
    assert normalize_polarity(raw).dtype == np.int8


@pytest.mark.parametrize("raw, match", [
    (np.array([-1, 0, 1]), "mixes -1, 0 and 1"),
    (np.array([0, 2]), "value 2"),
    (np.array([0.5, 1.0]), "non-integer value 0.5"),
    (np.array([np.nan, 1.0]), "non-integer value nan"),
    (np.array(["a"]), "bool or numeric"),
])
def test_polarity_rejects_with_the_bad_value(raw, match):
    with pytest.raises(InvalidInputError, match=match):
        normalize_polarity(raw)


def test_from_arrays_drops_and_counts_out_of_bounds():
    x = np.array([0, 345, 346, -1, 10], np.int16)
    y = np.array([0, 259, 0, 0, 260], np.int16)
    ev, st = Events.from_arrays([1, 2, 3, 4, 5], x, y, [1, 0, 1, 1, 0], width=346, height=260)
    assert ev.t.tolist() == [1, 2] and ev.x.tolist() == [0, 345] and ev.p.tolist() == [1, -1]
    assert (st.received, st.kept, st.out_of_bounds, st.dropped) == (5, 2, 3, 3)


def test_from_arrays_sorts_small_disorder_and_drops_large():
    tol = DEFAULT_MAX_DISORDER_US
    t = np.array([100, 200, 150, 300, 300 - tol - 1, 400], np.int64)  # 150: 50 µs behind; the 5th is too far
    ev, st = Events.from_arrays(t, np.arange(6), np.zeros(6, int), np.ones(6, bool), width=10, height=10)
    assert ev.t.tolist() == [100, 150, 200, 300, 400]
    assert ev.x.tolist() == [0, 2, 1, 3, 5]  # columns move with their timestamps
    assert (st.reordered, st.backwards, st.kept) == (1, 1, 5)


def test_from_arrays_late_events_counted():
    ev, st = Events.from_arrays([5, 10, 20], [0, 0, 0], [0, 0, 0], [1, 1, 1], width=1, height=1,
                                not_before_us=10)
    assert ev.t.tolist() == [10, 20] and st.late == 1 and st.dropped == 1


def test_stats_accumulate():
    a = EventStats(received=3, kept=2, late=1)
    a.add(EventStats(received=2, kept=2, reordered=1))
    assert a.as_dict() == {"received": 5, "kept": 4, "out_of_bounds": 0, "backwards": 0, "late": 1,
                           "reordered": 1, "dropped": 1}


def test_slicing_time_slice_concat_and_empty():
    ev = _ev([10, 20, 20, 30, 40])
    assert len(ev[1:3]) == 2 and ev[1:3].t.tolist() == [20, 20]
    assert np.shares_memory(ev[1:3].t, ev.t)  # views
    assert ev.time_slice(20, 40).t.tolist() == [20, 20, 30]  # half-open
    assert len(ev.time_slice(41, 50)) == 0
    assert Events.concat([ev[:2], Events.empty(), ev[2:]]) == ev
    with pytest.raises(InvalidInputError, match="before the previous batch ends"):
        Events.concat([ev[2:], ev[:2]])
    assert Events([], [], [], []) == Events.empty()
    e = Events.empty()
    assert len(e) == 0 and e.t_start is None and e.t_end is None and e.t.dtype == np.int64
    assert ev[ev.t > 15].t.tolist() == [20, 20, 30, 40]
    with pytest.raises(InvalidInputError, match="step 1"):
        ev[::-1]
    assert ev.shifted(5).t.tolist() == [15, 25, 25, 35, 45] and ev.t[0] == 10


def test_unix_epoch_microseconds_survive():
    t0 = 1_605_537_493_718_345
    ev = _ev([t0, t0 + 1])
    assert ev.t_start == t0 and ev.t_end - ev.t_start == 1
    with pytest.raises(InvalidInputError, match="outside"):
        Events(np.array([2**63], np.uint64), [0], [0], [1])
