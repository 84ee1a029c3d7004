"""Sensor-layer benchmark: ring ingest, the event map, HDF5 replay, ring memory.

    .venv/bin/python -m bench.sensor [--json PATH] [--quick]

Keys (targets): ring_ingest_mev_s >= 20 (million events/s pushed into the ring in
10k-event batches, about 10 ms of a busy DAVIS346), accumulate_1m_ms <= 5 (I_E of a 1M-event window at
346x260), h5_replay_mev_s >= 10 (our HDF5 replayed at factor 0), ring_peak_mb (RSS growth of a fresh
process whose ring is filled several times over: bounded by 13 bytes x capacity). Timings are medians
of repeats; on a shared machine they are noisy.
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.results import table, write_json
from edmcgs.sensor.buffer.ring import BYTES_PER_EVENT, EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import RecordingWriter
from edmcgs.sensor.sources.hdf5 import Hdf5Replay
from edmcgs.sensor.sources.pacing import Pacing

WIDTH, HEIGHT = 346, 260
TARGETS = {"ring_ingest_mev_s": (">=", 20.0), "accumulate_1m_ms": ("<=", 5.0),
           "h5_replay_mev_s": (">=", 10.0)}


def synthetic_events(n: int, *, t0: int = 1_700_000_000_000_000, rate_hz: float = 2e6,
                     seed: int = 0) -> Events:
    """n uniformly random events at 346x260, about rate_hz, sorted."""
    rng = np.random.default_rng(seed)
    t = t0 + np.sort(rng.integers(0, max(1, int(n / rate_hz * 1e6)), n, dtype=np.int64))
    x = rng.integers(0, WIDTH, n, dtype=np.uint16)
    y = rng.integers(0, HEIGHT, n, dtype=np.uint16)
    return Events._trusted(t, x, y, np.where(rng.random(n) < 0.5, np.int8(-1), np.int8(1)))


def bench_ring_ingest(total: int, batch: int, repeats: int) -> float:
    """Million events per second pushed (batches of `batch` events, the ring overflowing all along)."""
    ev = synthetic_events(batch)
    span = int(ev.t[-1] - ev.t[0]) + 1
    batches = [ev.shifted(i * span) for i in range(total // batch)]  # pre-built: time only the ring
    rates = []
    for _ in range(repeats):
        ring = EventRingBuffer(total // 4)
        t0 = time.perf_counter()
        for b in batches:
            ring.push(b)
        rates.append(total / (time.perf_counter() - t0) / 1e6)
    return statistics.median(rates)


def bench_accumulate(n: int, repeats: int) -> tuple[float, float]:
    ev = synthetic_events(n)
    accumulate(ev[:10], WIDTH, HEIGHT)  # compile (cached on disk after the first run)
    accumulate(ev[:10], WIDTH, HEIGHT, split_polarity=True)
    times, split = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        accumulate(ev, WIDTH, HEIGHT)
        times.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        accumulate(ev, WIDTH, HEIGHT, split_polarity=True)
        split.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), statistics.median(split)


def bench_h5_replay(n: int, repeats: int, folder: Path) -> float:
    path = folder / "bench.h5"
    ev = synthetic_events(n)
    with RecordingWriter(path, width=WIDTH, height=HEIGHT, sensor="bench") as w:
        for i in range(0, n, 1 << 20):
            w.append_events(ev[i:i + (1 << 20)])
    del ev
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        with Hdf5Replay(path, Pacing(factor=0)) as src:
            got = sum(len(b.events) for b in src)
        rates.append(got / (time.perf_counter() - t0) / 1e6)
        assert got == n, (got, n)
    return statistics.median(rates)


def _rss_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def _ring_memory_child(capacity: int, fills: int, queue) -> None:
    batch = synthetic_events(10_000)
    span = int(batch.t[-1] - batch.t[0]) + 1
    base = _rss_kb("VmRSS")
    ring = EventRingBuffer(capacity)
    for i in range(fills * capacity // len(batch)):
        ring.push(batch.shifted(i * span))
        if i % 50 == 0:  # a reader's copy of a 20 ms window (40k events) now and then: transient
            ring.slice(ring.watermark_us - 20_000, ring.watermark_us)
    queue.put(((_rss_kb("VmHWM") - base) / 1024, (_rss_kb("VmRSS") - base) / 1024, ring.stats().overflowed))


def bench_ring_memory(capacity: int, fills: int) -> tuple[float, float, int]:
    """(peak RSS growth MB, final RSS growth MB, events overflowed) in a fresh process."""
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_ring_memory_child, args=(capacity, fills, queue))
    proc.start()
    result = queue.get(timeout=600)
    proc.join()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.sensor", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--quick", action="store_true", help="smaller sizes (a smoke run, not for quoting)")
    args = parser.parse_args(argv)
    q = args.quick
    capacity = 2_000_000 if q else 10_000_000
    results: dict[str, float | int | str] = {}
    stages = ["ring ingest", "accumulate", "hdf5 replay", "ring memory"]
    with tempfile.TemporaryDirectory() as tmp, tqdm(stages, desc="bench.sensor", unit="stage") as bar:
        for stage in bar:
            bar.set_postfix_str(stage)
            if stage == "ring ingest":
                results["ring_ingest_mev_s"] = bench_ring_ingest(
                    4_000_000 if q else 20_000_000, 10_000, 3 if q else 5)
                results["ring_ingest_1k_batches_mev_s"] = bench_ring_ingest(
                    1_000_000 if q else 4_000_000, 1_000, 3)
            elif stage == "accumulate":
                results["accumulate_1m_ms"], results["accumulate_1m_split_ms"] = bench_accumulate(
                    1_000_000, 10 if q else 30)
            elif stage == "hdf5 replay":
                results["h5_replay_mev_s"] = bench_h5_replay(2_000_000 if q else 20_000_000, 2 if q else 3,
                                                             Path(tmp))
            else:
                peak, final, overflowed = bench_ring_memory(capacity, 4)
                results["ring_peak_mb"] = peak
                results["ring_final_mb"] = final
                results["ring_capacity_events"] = capacity
                results["ring_columns_mb"] = capacity * BYTES_PER_EVENT / 2**20
                results["ring_overflowed_events"] = overflowed
    results["quick"] = q
    print()
    print(table(results, TARGETS))
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
