"""Benchmark of many scenes on a local Ray Serve (``ray.init(num_cpus=2)``) against ``edmcgs-serve``.

    .venv/bin/python -m bench.ray_serve [--json PATH] [--seconds 8] [--clients 4]

Both scenes are the bundled demo (checkpoint + recording, 346x260), served as two scenes. Phases:

1. ``edmcgs-serve`` (one process, the demo): GET /render with 1 and ``--clients`` concurrent clients.
2. Ray Serve, 1 replica per scene: start-up (``ray.init`` to every replica up), the same loads on one
   scene through the gateway (``/scenes/a/render``), then both scenes loaded at once.
3. Ray Serve, 2 replicas per scene: the same, then one replica of scene ``a`` killed mid-load
   (``ray.kill``): failed requests (any non-200), the gateway's retries, and the seconds until its
   replacement answers.

Keys: ``*_rps`` requests per second, ``*_p50_ms`` / ``*_p99_ms`` client-side latency (HTTP included);
``overhead_p50_ms``: Ray's one-client p50 minus the single process's. The machine is shared and has 2
cores: 2 replicas per scene are 4 processes on them, so replicas add throughput only where cores are
free; quote the medians with the command.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from bench.results import table, write_json
from harness.server import ServerProcess

TARGETS = {"kill_failed_requests": ("<=", 0)}
T = 0.5  # seconds into the demo's span: every render's time (within the checkpoint's anchors)


def load(urls: list[str], clients_per_url: int, seconds: float, on_replica=None,
         stop: threading.Event | None = None) -> dict[str, dict]:
    """``clients_per_url`` threads per URL, each rendering back to back for ``seconds`` (or until
    ``stop`` is set); per URL: requests, rps, p50 / p99 latency (ms) and the failed ones (any status
    but 200)."""
    lat: dict[str, list[float]] = {u: [] for u in urls}
    failed: dict[str, list[int]] = {u: [] for u in urls}
    end = time.monotonic() + seconds
    stop = stop or threading.Event()

    def run(url: str) -> None:
        with httpx.Client(timeout=120) as client:
            while time.monotonic() < end and not stop.is_set():
                t0 = time.perf_counter()
                try:
                    r = client.get(url, params={"t": T, "format": "jpeg"})
                    status = r.status_code
                except httpx.HTTPError:
                    status = -1
                dt = time.perf_counter() - t0
                if status == 200:
                    lat[url].append(dt)
                    if on_replica is not None:
                        on_replica(r.headers.get("x-edmcgs-replica"))
                else:
                    failed[url].append(status)

    threads = [threading.Thread(target=run, args=(u,)) for u in urls for _ in range(clients_per_url)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    out = {}
    for u in urls:
        ms = np.asarray(lat[u]) * 1e3
        out[u] = {"requests": len(ms) + len(failed[u]), "rps": len(ms) / wall,
                  "p50_ms": float(np.percentile(ms, 50)) if len(ms) else float("nan"),
                  "p99_ms": float(np.percentile(ms, 99)) if len(ms) else float("nan"),
                  "failed": len(failed[u]), "failed_statuses": sorted(set(failed[u]))}
    return out


def _record(results: dict, prefix: str, m: dict) -> None:
    for key in ("rps", "p50_ms", "p99_ms"):
        results[f"{prefix}_{key}"] = round(m[key], 2)
    results[f"{prefix}_failed"] = m["failed"]


def single_process(results: dict, seconds: float, clients: int) -> None:
    server = ServerProcess([])
    try:
        server.wait_ready(timeout=300)
        url = server.url + "/render"
        load([url], 1, 2.0)  # warm
        _record(results, "single_1_client", load([url], 1, seconds)[url])
        _record(results, f"single_{clients}_clients", load([url], clients, seconds)[url])
    finally:
        server.stop()


def ray_phase(results: dict, replicas: int, seconds: float, clients: int, kill: bool) -> None:
    from harness.ray_serve import LocalServe, scene_entry

    scenes = [{**scene_entry(n, None, None, replicas=replicas, raster_threads=None),
               "cpus_per_replica": 1.0 / replicas} for n in ("a", "b")]
    tag = f"ray_{replicas}r"
    with LocalServe(scenes, num_cpus=2) as local:
        results[f"{tag}_startup_s"] = round(local.startup_s, 2)
        results[f"{tag}_ray_init_s"] = round(local.ray_init_s, 2)
        a, b = local.url + "/scenes/a/render", local.url + "/scenes/b/render"
        load([a, b], 1, 2.0)  # warm
        _record(results, f"{tag}_1_client", load([a], 1, seconds)[a])
        _record(results, f"{tag}_{clients}_clients", load([a], clients, seconds)[a])
        both = load([a, b], max(1, clients // 2), seconds)
        _record(results, f"{tag}_two_scenes_a", both[a])
        _record(results, f"{tag}_two_scenes_b", both[b])
        results[f"{tag}_two_scenes_total_rps"] = round(both[a]["rps"] + both[b]["rps"], 2)
        if kill:
            kill_mid_load(results, local, a, clients, seconds)


def kill_mid_load(results: dict, local, url: str, clients: int, seconds: float) -> None:
    """Kill one replica of scene a after ``seconds / 4`` of load; the load goes on until its
    replacement has answered (at least ``seconds``)."""
    seen: dict[str, float] = {}
    lock = threading.Lock()

    def on_replica(name):
        with lock:
            seen.setdefault(name, time.monotonic())

    retries0 = httpx.get(local.url + "/healthz", timeout=60).json()["retries"]
    box: dict = {}
    stop = threading.Event()
    thread = threading.Thread(target=lambda: box.update(m=load([url], clients, 300.0, on_replica, stop)))
    thread.start()
    time.sleep(seconds / 4)
    with lock:
        victim = sorted(seen)[0]
        before = set(seen)
    t_kill = time.monotonic()
    local.kill_replica(victim)
    replaced_s = float("nan")
    while time.monotonic() < t_kill + 240:
        with lock:
            new = {n: t for n, t in seen.items() if n not in before}
        if new and local.running_replicas("scene-a") >= 2:
            replaced_s = min(new.values()) - t_kill
            break
        time.sleep(0.1)
    time.sleep(max(0.0, t_kill + seconds - time.monotonic()))
    stop.set()
    thread.join()
    m = box["m"][url]
    results["kill_requests"] = m["requests"]
    results["kill_failed_requests"] = m["failed"]
    results["kill_failed_statuses"] = m["failed_statuses"]
    results["kill_replacement_answers_s"] = round(replaced_s, 2)
    retries = httpx.get(local.url + "/healthz", timeout=60).json()["retries"]
    results["kill_gateway_retries"] = retries - retries0
    results["kill_p99_ms"] = round(m["p99_ms"], 2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.ray_serve", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--seconds", type=float, default=8.0, help="duration of each measurement")
    p.add_argument("--clients", type=int, default=4, help="concurrent clients of the loaded runs")
    p.add_argument("--skip-single", action="store_true", help="leave out the single-process phase")
    args = p.parse_args(argv)
    results: dict = {"scene": "bundled demo (346x260), twice", "seconds": args.seconds,
                     "clients": args.clients}
    if not args.skip_single:
        print("edmcgs-serve ...", flush=True)
        single_process(results, args.seconds, args.clients)
    for replicas in (1, 2):
        print(f"ray, {replicas} replica(s) per scene ...", flush=True)
        ray_phase(results, replicas, args.seconds, args.clients, kill=replicas == 2)
    if "single_1_client_p50_ms" in results:
        results["overhead_p50_ms"] = round(results["ray_1r_1_client_p50_ms"]
                                           - results["single_1_client_p50_ms"], 2)
    print(table(results, TARGETS))
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
