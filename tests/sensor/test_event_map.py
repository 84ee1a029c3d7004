import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events


def _random_events(n, w, h, seed=0):
    rng = np.random.default_rng(seed)
    return Events(np.arange(n, dtype=np.int64), rng.integers(0, w, n), rng.integers(0, h, n),
                  rng.choice(np.array([-1, 1], np.int8), n))


def test_matches_a_reference_sum():
    w, h = 346, 260
    ev = _random_events(50_000, w, h)
    ref = np.zeros((h, w), np.int64)
    np.add.at(ref, (ev.y.astype(int), ev.x.astype(int)), ev.p.astype(int))
    out = accumulate(ev, w, h)
    assert out.dtype == np.float32 and out.shape == (h, w)
    np.testing.assert_array_equal(out, ref)
    split = accumulate(ev, w, h, split_polarity=True)
    assert split.shape == (2, h, w) and (split >= 0).all()
    np.testing.assert_array_equal(split[0] - split[1], ref)
    assert split.sum() == len(ev)


def test_empty_window_is_all_zeros():
    out = accumulate(Events.empty(), 8, 4)
    assert out.shape == (4, 8) and not out.any()
    assert not accumulate(Events.empty(), 8, 4, split_polarity=True).any()


def test_ten_million_events_on_one_pixel_are_exact():
    n = 10_000_000
    ev = Events._trusted(np.arange(n, dtype=np.int64), np.full(n, 3, np.uint16), np.full(n, 2, np.uint16),
                         np.ones(n, np.int8))
    out = accumulate(ev, 4, 4)
    assert out[2, 3] == n and out.sum() == n and np.isfinite(out).all()
    ev.p[: n // 2] = -1
    assert accumulate(ev, 4, 4)[2, 3] == 0
    split = accumulate(ev, 4, 4, split_polarity=True)
    assert split[0, 2, 3] == n // 2 and split[1, 2, 3] == n // 2


def test_event_outside_resolution_is_a_clear_error():
    ev = Events([1], [10], [0], [1])
    with pytest.raises(InvalidInputError, match="outside the 10x5 resolution"):
        accumulate(ev, 10, 5)
    with pytest.raises(InvalidInputError, match="resolution must be positive"):
        accumulate(ev, 0, 5)
    with pytest.raises(InvalidInputError, match="Events batch"):
        accumulate(np.zeros(3), 4, 4)
