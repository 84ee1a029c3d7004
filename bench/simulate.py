"""Event simulator and dataset builder benchmark.

    .venv/bin/python -m bench.simulate [--json PATH] [--quick]

Keys (targets): sim_mpix_s >= 20 (million pixel-samples per second through
``EventSimulator.step``: RGB float frame in, time-ordered events out, on the jumping jack's renders at
346x260 one millisecond apart, i.e. a frame in <= 5 ms), synth_small_s <= 60 (seconds to build the
small ``jumpingjack`` dataset at 5 fps, as ``edmcgs synth jumpingjack --fps 5`` does, without the
file write). Extras: the per-frame time, events per frame, the same with the passes parallel over
rows on numba's threads (``sim_parallel_*``), the simulator on noise frames (about two events per
pixel: the sort-heavy worst case), the build's render count and events. Timings are
medians of repeats; the machine's load average is recorded because a shared machine makes them noisy.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

from bench.results import table, write_json
from edmcgs.synth.build import BuildConfig, build_recording
from edmcgs.synth.esim import EventSimulator, SimulatorConfig
from edmcgs.synth.scene import make_scene, render

TARGETS = {"sim_mpix_s": (">=", 20.0), "sim_frame_ms": ("<=", 5.0), "synth_small_s": ("<=", 60.0)}


def _time_pass(frames: list[np.ndarray], step_us: int, parallel: bool) -> tuple[float, int]:
    """Seconds to step the simulator through ``frames`` (after a reset on the first), and events."""
    sim = EventSimulator(SimulatorConfig(), parallel=parallel)
    sim.reset(0, frames[0])
    n = 0
    t0 = time.perf_counter()
    for i, frame in enumerate(frames[1:], 1):
        n += len(sim.step(i * step_us, frame))
    return time.perf_counter() - t0, n


def bench_simulator(frames: list[np.ndarray], repeats: int,
                    parallel: bool = False) -> tuple[float, float, float]:
    """(million pixel-samples / s, ms per frame, events per frame), medians over ``repeats`` passes."""
    _time_pass(frames[:3], 1000, parallel)  # compile (cached on disk after the first run)
    h, w = frames[0].shape[:2]
    steps = len(frames) - 1
    runs = [_time_pass(frames, 1000, parallel) for _ in range(repeats)]
    secs = statistics.median(r[0] for r in runs)
    return steps * h * w / secs / 1e6, secs / steps * 1e3, runs[0][1] / steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.simulate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--quick", action="store_true", help="fewer repeats, a 0.4 s build (a smoke run)")
    args = parser.parse_args(argv)
    q = args.quick
    results: dict[str, float | int | str | bool] = {"load_avg_1m_start": os.getloadavg()[0],
                                                   "numba_threads": numba.get_num_threads()}
    stages = ["render frames", "simulator", "simulator parallel", "noise frames", "synth small"]
    with tqdm(stages, desc="bench.simulate", unit="stage") as bar:
        for stage in bar:
            bar.set_postfix_str(stage)
            if stage == "render frames":
                scene = make_scene("jumpingjack", "full")
                frames = [render(scene, 0.3 + 1e-3 * i) for i in range(21 if q else 61)]
            elif stage == "simulator":
                rate, frame_ms, per_frame = bench_simulator(frames, 3 if q else 9)
                results["sim_mpix_s"], results["sim_frame_ms"] = rate, frame_ms
                results["sim_events_per_frame"] = per_frame
            elif stage == "simulator parallel":
                rate, frame_ms, _ = bench_simulator(frames, 3 if q else 9, parallel=True)
                results["sim_parallel_mpix_s"], results["sim_parallel_frame_ms"] = rate, frame_ms
            elif stage == "noise frames":
                rng = np.random.default_rng(0)
                noise = [rng.random(frames[0].shape, dtype=np.float32) for _ in range(11)]
                rate, frame_ms, per_frame = bench_simulator(noise, 3 if q else 9)
                results["sim_noise_frame_ms"], results["sim_noise_events_per_frame"] = frame_ms, per_frame
            else:
                config = BuildConfig(scene="jumpingjack", fps=5.0, size="small",
                                     duration_s=0.4 if q else None)
                t0 = time.perf_counter()
                rec = build_recording(config, progress=False)
                results["synth_small_s"] = time.perf_counter() - t0
                results["synth_small_renders"] = rec.metadata["sampling"]["samples"]
                results["synth_small_events"] = len(rec.events)
                results["synth_small_anchors"] = len(rec.anchors)
                results["synth_small_gaussians"] = rec.metadata["gaussians"]
    results["load_avg_1m_end"] = os.getloadavg()[0]
    results["quick"] = q
    print()
    print(table(results, TARGETS))
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
