"""Benchmark of the service: a real ``edmcgs-serve`` process, driven over HTTP and the websocket.

    .venv/bin/python -m bench.serve [--json PATH] [--checkpoint CKPT --replay REC | --built] [--size WxH]
        [--device cpu|cuda]

Keys (targets, on the demo scene at 346x260, an idle 2-core CPU):
    render_p50_ms            GET /render, one client, the event branch included      <= 8
                             (render_{state,raster,encode}_mean_ms: where the server's
                             part of it goes, from its edmcgs_render_stage_seconds)
    render_rps_4_clients     four concurrent clients, each with its own pose          >= 200
    render_p99_ms_4_clients  the same, 99th percentile latency                        <= 150
    stream_fps               one websocket client, live mode asking for 60 fps        >= 60
    event_to_frame_ms        median, an event's arrival in the ring -> a live frame
                             that includes it, received by the client (the oldest
                             event new to each frame: it waits for the next frame's
                             start, up to a period, 16.7 ms at 60 fps, then for the
                             render)                                                  <= 15
    frame_age_ms             median, the arrival of the batch that brought a live
                             frame's time -> the frame received: how old the newest
                             information it shows is (the render and the send)

With ``--device cuda`` the server holds the model on the GPU (``edmcgs-serve --device cuda``: renders
through ``rasterize`` there, gsplat's where installed) and the targets are the GPU's: render_p50_ms <= 3,
render_rps_4_clients >= 500.

By default it serves the bundled demo scene and renders at ``--size`` 346x260. ``--built`` serves a
scene the bench builds from the model API instead (an untrained EdMCGS initialised from synthetic anchor
frames at 346x260 with the ``demo`` preset, 6000 Gaussians, and random events at ~300k ev/s;
``--gaussians 20000`` for a densified one); the numbers say which scene they come from. Client-side
latencies include HTTP; all clients run in this process.

The machine is shared: wall-clock numbers depend on what else runs. ``server_cpu_ms_per_*`` (CPU time
of the server process per render or frame, all threads) depend far less on it: on an idle 2-core
machine the throughput bound is about 2000 / that many renders per second.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.results import table, write_json
from harness.server import ServerProcess, build_scene, metric_values

TARGETS = {"render_p50_ms": ("<=", 8.0), "render_rps_4_clients": (">=", 200.0),
           "render_p99_ms_4_clients": ("<=", 150.0), "stream_fps": (">=", 60.0),
           "event_to_frame_ms": ("<=", 15.0)}
CUDA_TARGETS = TARGETS | {"render_p50_ms": ("<=", 3.0), "render_rps_4_clients": (">=", 500.0)}


STAGES = ("state", "raster", "encode")
"""The server's render stages (``edmcgs_render_stage_seconds``): the one-client phase reports their means."""


def _percentile(values, q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else float("nan")


def _orbit_pose(scene: dict, angle: float, t_us: int) -> list[float]:
    """The event camera's pose at t, turned by ``angle`` about the vertical through a point 1 m ahead."""
    traj = scene["trajectory"]
    i = int(np.clip(np.searchsorted(traj["t_us"], t_us), 0, len(traj["t_us"]) - 1))
    c2w = np.asarray(traj["c2w"][i]).reshape(4, 4)
    pivot = c2w[:3, :3] @ np.array([0.0, 0.0, 1.0]) + c2w[:3, 3]
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    out = np.eye(4)
    out[:3, :3] = rot @ c2w[:3, :3]
    out[:3, 3] = rot @ (c2w[:3, 3] - pivot) + pivot
    return out.reshape(-1).tolist()


def measure_single(client, scene: dict, seconds: float, size: tuple[int, int]) -> dict:
    """One client, GET /render as JPEG at a new time each request (no cache hit: deform every time).
    Times come from the renderable span the scene reported; when the replay has moved on past one (the
    ring forgets the oldest events: a fast replay of a busy recording), the span is read again and that
    request, answered 416, is counted apart (``render_refused_1_client``) rather than timed."""
    from edmcgs.clients.client import TimeUnavailable

    r = scene["renderable"]
    lo, hi = r["t_us_min"], r["t_us_max"]
    latencies, server_ms, events = [], [], []
    k, refused, t_end = 0, 0, time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t_us = lo + (k * 7_919) % (hi - lo)  # a prime step: every request a new instant
        k += 1
        t0 = time.perf_counter()
        try:
            _, meta = client.render(t_us=t_us, width=size[0], height=size[1], format="jpeg")
        except TimeUnavailable:
            refused += 1
            r = client.scene()["renderable"]
            lo, hi = r["t_us_min"], r["t_us_max"]
            continue
        latencies.append((time.perf_counter() - t0) * 1e3)
        server_ms.append(meta.render_ms)
        events.append(meta.events)
    return {"render_p50_ms": _percentile(latencies, 50), "render_p90_ms_1_client": _percentile(latencies, 90),
            "render_server_p50_ms": _percentile(server_ms, 50), "render_requests_1_client": len(latencies),
            "render_refused_1_client": refused, "events_per_render_median": _percentile(events, 50)}


def stage_means(before: dict[str, float], after: dict[str, float]) -> dict:
    """Mean milliseconds per render of each stage the server times (``edmcgs_render_stage_seconds``)
    between two scrapes: where the server-side render time goes."""
    out = {}
    for stage in STAGES:
        key = f'{{stage="{stage}"}}'
        n = after.get(f"edmcgs_render_stage_seconds_count{key}", 0) - before.get(
            f"edmcgs_render_stage_seconds_count{key}", 0)
        total = after.get(f"edmcgs_render_stage_seconds_sum{key}", 0) - before.get(
            f"edmcgs_render_stage_seconds_sum{key}", 0)
        out[f"render_{stage}_mean_ms"] = total * 1e3 / n if n else float("nan")
    return out


def measure_four(url: str, token: str | None, scene: dict, seconds: float, size: tuple[int, int],
                 clients: int = 4) -> dict:
    """Four clients orbiting their own poses around the same instant, which moves on twice a second
    (viewers scrubbing a slow-motion playback together): the deformation is shared, the renders not."""
    from edmcgs.clients.client import Client

    r = scene["renderable"]
    lo, hi = r["t_us_min"], r["t_us_max"]
    latencies: list[list[float]] = [[] for _ in range(clients)]
    start = time.perf_counter()
    stop = start + seconds

    def run(i: int) -> None:
        with Client(url, token=token, timeout=30) as client:
            n = 0
            while (now := time.perf_counter()) < stop:
                step = int((now - start) * 2)  # the shared instant: 2 steps per second
                t_us = lo + (step * 33_333) % (hi - lo)
                pose = _orbit_pose(scene, 0.3 * math.sin(0.5 * n + i * math.pi / 2), t_us)
                t0 = time.perf_counter()
                client.render(t_us=t_us, pose=pose, width=size[0], height=size[1], format="jpeg")
                latencies[i].append((time.perf_counter() - t0) * 1e3)
                n += 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(clients)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    elapsed = time.perf_counter() - start
    flat = [v for per in latencies for v in per]
    return {"render_rps_4_clients": len(flat) / elapsed, "render_p50_ms_4_clients": _percentile(flat, 50),
            "render_p99_ms_4_clients": _percentile(flat, 99), "render_requests_4_clients": len(flat)}


def measure_stream(client, seconds: float, size: tuple[int, int]) -> dict:
    """One websocket client in live mode asking for 60 fps (JPEG, the event camera's pose)."""
    frames, latencies, ages = 0, [], []
    sub = {"mode": "live", "fps": 60, "format": "jpeg", "width": size[0], "height": size[1]}
    with client.stream(sub) as stream:
        assert stream.receive(timeout=30) is not None  # first frame: not timed
        start = time.perf_counter()
        while time.perf_counter() - start < seconds:
            frame = stream.receive(timeout=30)
            received_us = time.time_ns() // 1000
            frames += 1
            if frame.arrived_unix_us is not None:
                latencies.append((received_us - frame.arrived_unix_us) / 1e3)
            if frame.head_arrived_unix_us is not None:
                ages.append((received_us - frame.head_arrived_unix_us) / 1e3)
        elapsed = time.perf_counter() - start
        dropped = frame.dropped
    return {"stream_fps": frames / elapsed, "event_to_frame_ms": _percentile(latencies, 50),
            "event_to_frame_p90_ms": _percentile(latencies, 90), "frame_age_ms": _percentile(ages, 50),
            "frame_age_p90_ms": _percentile(ages, 90), "stream_frames": frames,
            "stream_frames_dropped": dropped}


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.serve", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--checkpoint", type=Path,
                   help="serve this checkpoint (with --replay; default: the bundled demo scene)")
    p.add_argument("--built", action="store_true",
                   help="serve a scene built by the bench (untrained) instead of the demo")
    p.add_argument("--size", type=_size, default=(346, 260), help="rendered WIDTHxHEIGHT (default 346x260)")
    p.add_argument("--replay", type=Path, help="its recording")
    p.add_argument("--seconds", type=float, default=8.0, help="duration of each measurement")
    p.add_argument("--gaussians", type=int, help="Gaussians of the built scene (default: the demo preset's "
                                                 "6000; a trained demo has up to 30k)")
    p.add_argument("--device", default="cpu", help="the server's torch device (edmcgs-serve --device)")
    args = p.parse_args(argv)
    from edmcgs.errors import InvalidInputError
    from edmcgs.model.devices import check_device

    try:
        check_device(args.device)
    except InvalidInputError as exc:
        p.error(str(exc))
    from tqdm import tqdm

    from edmcgs.clients.client import Client

    steps = tqdm(total=5, desc="bench.serve", unit="step")
    with tempfile.TemporaryDirectory(prefix="bench-serve-") as tmp:
        if args.checkpoint is None and not args.built:
            from edmcgs.server import demo

            args.checkpoint, args.replay = demo.files()
        if args.built:
            steps.set_postfix_str("building the scene")
            rec, ckpt = build_scene(tmp, init_points=args.gaussians)
            scene_name = "bench.serve synthetic: untrained EdMCGS, demo preset, 346x260, 300k ev/s"
        else:
            if args.replay is None:
                p.error("--checkpoint needs --replay")
            rec, ckpt, scene_name = args.replay, args.checkpoint, str(args.checkpoint)
        steps.update()
        steps.set_postfix_str("starting edmcgs-serve")
        server = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop", "--device",
                                args.device])
        try:
            server.wait_ready()
            with Client(server.url, timeout=30) as client:
                scene = client.scene()
                # Let the replay cover its whole first pass, so every time of the scene is renderable.
                while (client.scene()["renderable"] or {}).get("t_us_max", 0) < scene["t_end_us"] - 20_000:
                    time.sleep(0.1)
                scene = client.scene()
                steps.update()
                steps.set_postfix_str("one client")
                cpu0, stages0 = server.cpu_s(), metric_values(client.metrics())
                results = measure_single(client, scene, args.seconds, args.size)
                cpu1 = server.cpu_s()
                results |= stage_means(stages0, metric_values(client.metrics()))
                results["server_cpu_ms_per_render_1_client"] = \
                    (cpu1 - cpu0) * 1e3 / results["render_requests_1_client"]
                steps.update()
                steps.set_postfix_str("four clients")
                results |= measure_four(server.url, None, scene, args.seconds, args.size)
                cpu2 = server.cpu_s()
                results["server_cpu_ms_per_render_4_clients"] = \
                    (cpu2 - cpu1) * 1e3 / results.pop("render_requests_4_clients")
                steps.update()
                steps.set_postfix_str("websocket")
                results |= measure_stream(client, args.seconds, args.size)
                results["server_cpu_ms_per_frame_stream"] = \
                    (server.cpu_s() - cpu2) * 1e3 / results["stream_frames"]
                steps.update()
                metrics = client.metrics()
        finally:
            code = server.stop()
        steps.close()
    cache = {line.split("{")[1].split("}")[0]: float(line.rsplit(" ", 1)[1]) for line in metrics.splitlines()
             if line.startswith("edmcgs_deform_cache_total{")}
    results |= {
        "deform_cache_hits": cache.get('result="hit"', 0.0),
        "deform_cache_misses": cache.get('result="miss"', 0.0),
        "scene": scene_name, "device": args.device, "width": args.size[0], "height": args.size[1],
        "num_gaussians": scene["num_gaussians"], "has_event_branch": scene["has_event_branch"],
        "seconds_per_measurement": args.seconds, "cpus": os.cpu_count(),
        "load_average_1m": os.getloadavg()[0], "server_exit_code": code,
    }
    print(table(results, TARGETS if args.device == "cpu" else CUDA_TARGETS))
    print(f"scene: {scene_name}, {results['num_gaussians']} Gaussians; load average "
          f"{results['load_average_1m']:.1f} on {os.cpu_count()} CPUs (a shared machine: medians are noisy)")
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
