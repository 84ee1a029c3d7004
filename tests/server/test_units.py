"""Unit tests of the service's pure parts: state cache, wire schema."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from edmcgs import protocol
from edmcgs.server.encode import to_uint8
from edmcgs.server.state_cache import StateCache

T0 = 1_600_000_000_000_000


def test_state_cache_computes_once_for_concurrent_callers():
    cache = StateCache(2)
    calls = []

    def compute():  # holds the key until the five other callers wait on it (each counted as a hit)
        calls.append(1)
        deadline = time.monotonic() + 60
        while cache.hits < 5 and time.monotonic() < deadline:
            time.sleep(1e-3)
        return object()

    results = []
    threads = [threading.Thread(target=lambda: results.append(cache.get("k", compute))) for _ in range(6)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(calls) == 1 and len({id(r) for r in results}) == 1
    assert (cache.misses, cache.hits) == (1, 5)
    cache.get("a", object)
    cache.get("b", object)
    assert len(cache) == 2 and cache.get("k", lambda: "recomputed") == "recomputed"  # evicted, LRU


def test_state_cache_does_not_keep_failures():
    cache = StateCache(4)

    def boom():
        raise RuntimeError("no")

    with pytest.raises(RuntimeError):
        cache.get("k", boom)
    assert cache.get("k", lambda: 3) == 3


def test_subscription_validation_names_the_field():
    sub = protocol.Subscription().updated({"mode": "sweep", "t0": 0, "t1": 1.5,
                                           "pose": [0, 0, 0, 1, 0, 0, 0]})
    assert sub.mode == "sweep" and sub.pose == [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    assert sub.updated({"fps": 12}).t1 == 1.5  # partial updates keep the rest
    for bad, field in (({"mode": "replay"}, "mode"), ({"fps": 0}, "fps"), ({"fps": float("nan")}, "fps"),
                       ({"width": 1.5}, "width"), ({"loop": "yes"}, "loop"), ({"pose": [1, 2]}, "pose"),
                       ({"pose": [float("inf")] * 16}, "pose"), ({"format": "gif"}, "format"),
                       ({"speed": -1}, "speed"), ({"colour": 1}, "colour"), ({"t0": True}, "t0")):
        with pytest.raises(protocol.ProtocolError) as info:
            sub.updated(bad)
        assert info.value.param == field
    with pytest.raises(protocol.ProtocolError):
        protocol.decode_message(b"\xc1")


def test_accept_negotiation_and_pose_text():
    assert protocol.negotiate_format(None) == "png"
    assert protocol.negotiate_format("image/jpeg") == "jpeg"
    assert protocol.negotiate_format("application/msgpack;q=0.5, image/jpeg;q=0.9") == "jpeg"
    assert protocol.negotiate_format("image/jpeg;q=0, */*") == "png"
    assert protocol.negotiate_format("application/x-msgpack") == "msgpack"
    assert protocol.parse_pose_text("1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1")[5] == 1.0
    assert protocol.parse_pose_text("[0, 0, 0, 1, 0, 0, 0]") == [0, 0, 0, 1, 0, 0, 0]
    with pytest.raises(protocol.ProtocolError):
        protocol.parse_pose_text("1,2,x,4,5,6,7")


def test_arrivals_date_a_stream_time_by_the_batch_that_brought_it():
    from edmcgs.server.live.signal import Arrivals

    clock = iter(range(1_000, 10_000, 1_000))  # Unix µs of each arrival
    arrivals = Arrivals(keep=3, clock=lambda: next(clock))
    for until in (100, 200, 300, 400):  # batches [0, 100), [100, 200), ... complete up to ``until``
        arrivals.record(until)
    assert arrivals.arrival_of(250) == arrivals.arrival_of(299) == 3_000
    assert arrivals.arrival_of(300) == 4_000  # the batch [300, 400), not the one complete up to 300
    assert arrivals.arrival_of(400) is None  # not arrived yet
    # Bounded: the batch complete until 100 is forgotten, the oldest kept one (200) answers instead.
    assert arrivals.arrival_of(50) == arrivals.arrival_of(150) == 2_000


def test_ring_first_time_is_the_oldest_event_in_a_window():
    from edmcgs.sensor.buffer.ring import EventRingBuffer
    from edmcgs.sensor.events import Events

    ring = EventRingBuffer(4)
    assert ring.first_time(0, 100) is None
    t = np.array([10, 20, 30, 40, 50, 60], np.int64)  # six into four: 10 and 20 are dropped
    n = len(t)
    ring.push(Events(t, np.zeros(n, np.uint16), np.zeros(n, np.uint16), np.ones(n, np.int8)),
              complete_until_us=61)
    assert ring.first_time(0, 100) == 30  # the oldest retained
    assert ring.first_time(31, 100) == 40 and ring.first_time(40, 41) == 40
    assert ring.first_time(41, 50) is None and ring.first_time(61, 100) is None


def test_head_signal_wakes_waiters_from_another_thread():
    import asyncio

    from edmcgs.server.live.signal import HeadSignal

    async def scenario():
        signal = HeadSignal(asyncio.get_running_loop())
        waiting = asyncio.ensure_future(signal.wait(60.0))
        await asyncio.sleep(0)  # the waiter is parked on the signal
        notifier = threading.Thread(target=signal.notify)
        notifier.start()
        woke = await waiting
        notifier.join()
        timed_out = not await signal.wait(0.01)  # nobody notifies: the timeout
        return woke, timed_out

    assert asyncio.run(scenario()) == (True, True)


def test_to_uint8_rounds_clips_and_zeroes_non_finite_pixels():
    img = np.array([[[0.0, 0.5, 1.0], [np.nan, np.inf, -np.inf]], [[-0.2, 1.7, 0.999], [2e-3, 0.1, 0.9]]],
                   np.float32)
    out = to_uint8(img)
    assert out.dtype == np.uint8
    assert out.tolist() == [[[0, 128, 255], [0, 255, 0]], [[0, 255, 255], [1, 26, 230]]]
