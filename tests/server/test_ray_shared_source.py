"""A live source shared by a scene's replicas, in-process: the shared ring and a replica's reader
(``RemoteSource``) over a stand-in for the Serve handle (no Ray needed)."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
import pytest

from edmcgs.errors import SensorError
from edmcgs.sensor.events import Events
from edmcgs.sensor.sources.base import Extras, SensorBatch, StreamInfo
from edmcgs.server.ray_serve.shared_source import RemoteSource, SharedRing

INFO = StreamInfo(width=8, height=6, sensor="test", has_frames=False, has_imu=False, live=True)


def batch(t0: int, n: int = 3) -> SensorBatch:
    t = np.arange(t0, t0 + n, dtype=np.int64)
    z = np.zeros(n, np.uint16)
    return SensorBatch(events=Events(t, z, z, np.ones(n, np.int8)))


class Call:
    def __init__(self, value):
        self.value = value

    def result(self, timeout_s=None):
        return self.value


class Method:
    def __init__(self, fn):
        self.fn = fn

    def remote(self, *args):
        return Call(self.fn(*args))


class Handle:
    """What ``RemoteSource`` uses of a DeploymentHandle to ``SceneIngest``."""

    def __init__(self, shared: SharedRing):
        self.info = Method(lambda: INFO)
        self.extras = Method(Extras)
        self.pull = Method(lambda after, wait_s: asyncio.run(shared.pull(after, 0.0)))


def test_every_reader_gets_every_batch_in_order():
    shared = SharedRing()
    readers = [RemoteSource(Handle(shared), "cam"), RemoteSource(Handle(shared), "cam")]
    for i in range(5):
        shared.append(batch(100 * i))
    for reader in readers:
        got = [int(reader.read().events.t[0]) for _ in range(5)]
        assert got == [0, 100, 200, 300, 400] and reader.missed_batches == 0
        assert len(reader.read().events) == 0, "nothing new yet: an empty batch, the stream still open"
    shared.finish()
    assert readers[0].read() is None


def test_a_reader_that_falls_behind_says_what_it_missed(caplog):
    shared = SharedRing(capacity=4, join=4)
    reader = RemoteSource(Handle(shared), "cam")
    shared.append(batch(0))
    assert int(reader.read().events.t[0]) == 0
    for i in range(1, 10):
        shared.append(batch(100 * i, n=2))  # seq 1..9; the ring keeps 6..9
    with caplog.at_level(logging.WARNING, "edmcgs.server.ray"):
        assert int(reader.read().events.t[0]) == 600
    assert reader.missed_batches == 5 and reader.missed_events == 10
    assert "fell behind the shared source and missed 5 batches (10 events)" in caplog.text
    assert [int(reader.read().events.t[0]) for _ in range(3)] == [700, 800, 900]
    assert reader.missed_batches == 5, "no more missed once caught up"


def test_a_late_reader_joins_inside_the_ring_and_keeps_up_while_it_moves_on(monkeypatch):
    """Joining at the oldest batch held, the next to leave, a reader whose pulls are capped would lose
    batches as soon as the source appended between its first two pulls; it joins ``join`` behind the
    head instead."""
    from edmcgs.server.ray_serve import shared_source

    monkeypatch.setattr(shared_source, "PULL_MAX", 2)
    shared = SharedRing(capacity=8, join=4)
    for i in range(20):
        shared.append(batch(100 * i))  # seq 0..19; the ring keeps 12..19
    reader = RemoteSource(Handle(shared), "cam")
    assert [int(reader.read().events.t[0]) for _ in range(2)] == [1600, 1700]  # its first pull: 16, 17
    for i in range(20, 23):  # the source goes on before the next pull; the ring keeps 15..22
        shared.append(batch(100 * i))
    assert [int(reader.read().events.t[0]) for _ in range(5)] == [1800, 1900, 2000, 2100, 2200]
    assert reader.missed_batches == 0
    young = SharedRing(capacity=8, join=4)  # fewer batches than ``join``: from the first
    young.append(batch(0))
    assert int(RemoteSource(Handle(young), "cam").read().events.t[0]) == 0


@pytest.mark.parametrize("join", [0, 9])
def test_a_join_outside_the_ring_is_refused(join):
    with pytest.raises(ValueError, match="joins 1 to capacity"):
        SharedRing(capacity=8, join=join)


def test_the_sources_failure_reaches_every_reader():
    shared = SharedRing()
    reader = RemoteSource(Handle(shared), "cam")
    shared.finish("SensorError: the camera went away")
    with pytest.raises(SensorError, match="the camera went away"):
        reader.read()


class Replaceable:
    """A handle whose ingest replica can die (every call fails) and be replaced by one with a new ring."""

    def __init__(self, shared: SharedRing):
        self.shared, self.dead_calls = shared, 0
        self.info = Method(lambda: self._call(lambda: INFO))
        self.extras = Method(lambda: self._call(Extras))
        self.pull = Method(lambda after, wait_s: self._call(
            lambda: asyncio.run(self.shared.pull(after, 0.0))))

    def _call(self, fn):
        if self.dead_calls:
            self.dead_calls -= 1
            raise RuntimeError("ActorDiedError: the replica died")
        return fn()


def test_a_replaced_ingest_replica_is_reconnected_and_read_from_its_first_batch(caplog):
    from edmcgs.errors import DeviceDisconnected
    from edmcgs.sensor.buffer.ingest import Ingest
    from edmcgs.sensor.buffer.ring import EventRingBuffer

    first = SharedRing()
    handle = Replaceable(first)
    reader = RemoteSource(handle, "cam")
    for i in range(3):
        first.append(batch(100 * i))
    assert [int(reader.read().events.t[0]) for _ in range(3)] == [0, 100, 200]
    first.append(batch(300))  # held by the replica that dies: never handed over
    handle.dead_calls = 3  # the pull, then two probes of the reconnect
    with pytest.raises(DeviceDisconnected, match="ingest replica did not answer"):
        reader.read()
    handle.shared = second = SharedRing()
    for i in range(4, 6):
        second.append(batch(100 * i))
    with caplog.at_level(logging.WARNING, "edmcgs.server.ray"):
        reader.reconnect(initial_delay_s=0.0)
        assert handle.dead_calls == 0
        assert [int(reader.read().events.t[0]) for _ in range(2)] == [400, 500]
    assert reader.reconnects == 1 and reader.missed_batches == 0  # a restart is not a ring's fall-behind
    assert "the shared source restarted" in caplog.text

    # the same through a replica's ingest thread: the disconnect is counted, nothing ends in an error
    third = SharedRing()
    handle.shared = third
    ring = EventRingBuffer(1000)
    ingest = Ingest(RemoteSource(handle, "cam"), ring)
    handle.dead_calls = 1  # its first pull
    for i in range(6, 9):
        third.append(batch(100 * i))
    third.finish()
    ingest.run()
    assert ingest.error is None and ingest.finished and ingest.disconnects == 1
    assert ingest.source.reconnects == 1  # the same ring again: counted once
    assert ring.stats().size == 9 and ring.stats().oldest_us == 600


def test_an_ingest_replica_that_never_comes_back_is_a_source_failure():
    handle = Replaceable(SharedRing())
    reader = RemoteSource(handle, "cam")
    handle.dead_calls = 10**6
    with pytest.raises(SensorError, match="did not come back"):
        reader.reconnect(budget_s=0.05, initial_delay_s=0.01)
