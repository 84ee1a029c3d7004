import threading
import time

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError, WindowUnavailable
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.events import Events


def _stream(n, *, t0=1_700_000_000_000_000, step=3, seed=0):
    """n events, several per timestamp (t = t0 + step * (i // 4)), coordinates encode the index."""
    i = np.arange(n)
    rng = np.random.default_rng(seed)
    p = rng.choice(np.array([-1, 1], np.int8), n)
    return Events(t0 + step * (i // 4), i % 1000, (i // 1000) % 1000, p)


def _reference(ev, t0, t1):
    return ev.time_slice(t0, t1)


def test_slice_is_half_open_and_matches_reference_across_wraps():
    ev = _stream(10_000)
    ring = EventRingBuffer(2_500)
    rng = np.random.default_rng(1)
    pos = 0
    while pos < len(ev):
        n = int(rng.integers(1, 700))
        ring.push(ev[pos:pos + n])
        pos += n
        oldest, wm = ring.oldest_us, ring.watermark_us
        lo = oldest + 1 if ring.stats().overflowed else oldest  # events at `oldest` may be partly dropped
        for _ in range(5):
            a = int(rng.integers(lo, wm + 1))
            b = int(rng.integers(a, wm + 1))
            assert ring.slice(a, b) == _reference(ev[:pos], a, b)
    assert len(ring) == 2_500 and ring.head_us == ev.t_end
    st = ring.stats()
    assert st.pushed == 10_000 and st.overflowed == 7_500 and st.size == 2_500 and st.fill == 1.0


def test_empty_and_exact_boundaries():
    ring = EventRingBuffer(100)
    with pytest.raises(WindowUnavailable, match="no events received yet"):
        ring.slice(0, 10)
    ring.push(Events([10, 20, 20, 30], [0, 1, 2, 3], [0] * 4, [1, 1, -1, 1]))
    assert ring.slice(20, 30).x.tolist() == [1, 2]
    assert ring.slice(10, 10) == Events.empty()
    # nothing was ever dropped: the time before the first event is known to be empty
    assert ring.slice(0, 10) == Events.empty()
    with pytest.raises(InvalidInputError, match="before its start"):
        ring.slice(30, 20)


def test_window_past_the_watermark_is_refused_until_complete():
    ring = EventRingBuffer(100)
    ring.push(Events([10, 20], [0, 0], [0, 0], [1, 1]))
    assert ring.watermark_us == 20
    with pytest.raises(WindowUnavailable, match="complete only for t < 20"):
        ring.slice(0, 21)  # more events at t=20 may still come
    ring.push(Events.empty(), complete_until_us=25)
    assert ring.slice(0, 25).t.tolist() == [10, 20]
    ring.mark_complete(1_000)
    assert ring.count(0, 1_000) == 2


def test_overflow_drops_oldest_counts_them_and_refuses_old_windows():
    ring = EventRingBuffer(4)
    ring.push(Events([1, 2, 3, 4, 5, 6], [0] * 6, [0] * 6, [1] * 6))  # larger than capacity in one push
    st = ring.stats()
    assert st.overflowed == 2 and ring.oldest_us == 3 and ring.head_us == 6
    with pytest.raises(WindowUnavailable, match=r"no longer retained.*newest 4 events.*t >= 3"):
        ring.slice(2, 5)
    ring.mark_complete(7)
    assert ring.slice(3, 7).t.tolist() == [3, 4, 5, 6]
    ring.push(Events([7, 8], [0, 0], [0, 0], [1, 1]))
    assert ring.stats().overflowed == 4
    with pytest.raises(WindowUnavailable):
        ring.slice(4, 6)


def test_same_timestamp_split_by_overflow_is_not_served_as_complete():
    ring = EventRingBuffer(3)
    ring.push(Events([5, 5, 5, 5], [0, 1, 2, 3], [0] * 4, [1] * 4))
    ring.mark_complete(6)
    with pytest.raises(WindowUnavailable):
        ring.slice(5, 6)  # one of the t=5 events was dropped
    ring.push(Events([9], [0], [0], [1]))
    ring.mark_complete(10)
    assert ring.slice(6, 10).t.tolist() == [9]


def test_retention_in_time():
    ring = EventRingBuffer(1_000, retention_us=100)
    ring.push(Events(np.arange(0, 500, 10), np.zeros(50, int), np.zeros(50, int), np.ones(50, int)))
    assert ring.oldest_us == 390 and ring.stats().expired == 39 and ring.stats().overflowed == 0
    with pytest.raises(WindowUnavailable, match="100 µs"):
        ring.slice(300, 400)
    assert ring.slice(390, 490).t.tolist() == list(range(390, 490, 10))


def test_late_events_are_dropped_and_counted():
    ring = EventRingBuffer(100)
    ring.push(Events([10, 20], [0, 0], [0, 0], [1, 1]), complete_until_us=30)
    assert ring.push(Events([25, 30, 40], [0, 0, 0], [0, 0, 0], [1, 1, 1])) == 2
    assert ring.stats().late == 1 and ring.head_us == 40


def test_validation():
    with pytest.raises(InvalidInputError, match="capacity"):
        EventRingBuffer(0)
    with pytest.raises(InvalidInputError, match="Events batch"):
        EventRingBuffer(4).push(np.zeros(3))


def test_one_writer_many_readers_get_consistent_windows():
    ev = _stream(400_000, step=1)
    ring = EventRingBuffer(50_000)
    stop = threading.Event()
    errors: list[str] = []
    served = [0]

    def writer():
        for i in range(0, len(ev), 997):
            ring.push(ev[i:i + 997])
            time.sleep(1e-4)  # let the readers interleave with the writer
        stop.set()

    def reader(seed):
        rng = np.random.default_rng(seed)
        try:
            while not stop.is_set() or served[0] == 0:
                st = ring.stats()
                if st.watermark_us is None:
                    continue
                a = int(rng.integers(st.oldest_us - 2_000, st.watermark_us))
                b = min(st.watermark_us, a + int(rng.integers(0, 20_000)))
                try:
                    got = ring.slice(a, b)
                except WindowUnavailable:
                    continue  # overwritten meanwhile: refused, never torn
                want = _reference(ev, a, b)
                if got != want:
                    errors.append(f"window [{a}, {b}): {len(got)} events, expected {len(want)}")
                served[0] += 1
        except Exception as exc:  # a crashed reader must fail the test, not vanish
            errors.append(repr(exc))

    threads = [threading.Thread(target=writer)]
    threads += [threading.Thread(target=reader, args=(s,)) for s in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors, errors[:3]
    assert served[0] > 100
    st = ring.stats()
    assert st.pushed == len(ev) and st.overflowed == len(ev) - 50_000 and st.size == 50_000


def test_anchor_store_tau_and_eviction():
    store = AnchorStore(capacity=3)
    img = np.zeros((4, 5, 3), np.uint8)
    assert store.tau(100) is None
    with pytest.raises(WindowUnavailable, match="no anchor received yet"):
        store.anchor_at(100)
    for t in (100, 200, 300):
        store.add(t, img + t // 100, np.eye(4) if t == 200 else None)
    assert store.tau(99) is None and store.tau(100) == 100
    assert store.tau(250) == 200 and store.tau(10**15) == 300
    a = store.anchor_at(299)
    assert a.t_us == 200 and a.image[0, 0, 0] == 2 and np.array_equal(a.pose, np.eye(4))
    assert store.next_after(200) == 300 and store.next_after(300) is None
    with pytest.raises(WindowUnavailable, match="first anchor is at 100"):
        store.anchor_at(50)
    store.add(400, img)
    assert store.evicted == 1 and store.times().tolist() == [200, 300, 400]
    with pytest.raises(WindowUnavailable, match="evicted"):
        store.tau(150)
    with pytest.raises(InvalidInputError, match="not after"):
        store.add(400, img)
    with pytest.raises(InvalidInputError, match="uint8"):
        store.add(500, img.astype(np.float32))
    store.add(500, np.zeros((4, 5), np.uint8))  # grey is given a channel axis
    assert store.latest.image.shape == (4, 5, 1)
