"""Soak: HTTP clients rendering in a loop, websocket streams and idle sockets against one edmcgs-serve,
for a while; reports every status seen, the 503s, the 5xx, the server's RSS growth after warm-up, and
the latency of a probe (GET /healthz, then GET /render) every half second.

    .venv/bin/python scripts/soak.py [--seconds 180] [--warmup 30] [--clients 4] [--streams 10]
                                     [--idle 200] [--token] [--probe-limit-s 1]

``--idle N`` holds N connections that never finish a request, half silent and half with half a request
line, opening a new one whenever the server closes one (it does after its head_timeout_s). ``--token``
runs the server with EDMCGS_TOKEN and every client with it. Exits non-zero when a /render answered 503,
anything answered 5xx, a probe did not answer 200 (or took longer than ``--probe-limit-s``), or RSS grew
5 % or more after the warm-up. The scene is the tests' tiny synthetic one (harness.server).
All load goes to 127.0.0.1; every loop ends with the run.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import httpx
import websockets

from edmcgs import protocol
from edmcgs.server.connections import raise_fd_limit
from harness.server import HEIGHT, TOKEN, WIDTH, ServerProcess, build_scene

PROBE_EVERY_S = 0.5
IDLE_CHECK_S = 1.0


def http_client(url: str, headers: dict, stop: threading.Event, statuses: collections.Counter,
                lock: threading.Lock, k: int) -> None:
    with httpx.Client(base_url=url, timeout=30, headers=headers) as c:
        i = 0
        while not stop.is_set():
            t = 0.05 + (i * 0.173 + k * 0.31) % 1.9
            r = c.get("/render", params={"t": f"{t:.3f}", "format": "jpeg" if i % 2 else "png"})
            with lock:
                statuses[r.status_code] += 1
            i += 1


def probe(url: str, headers: dict, stop: threading.Event, seen: dict) -> None:
    """GET /healthz and GET /render every PROBE_EVERY_S on a new connection each: a real client's
    first request, whatever else holds the server's connections."""
    while not stop.is_set():
        for path, params in (("/healthz", None), ("/render", {"t": "0.5", "format": "jpeg"})):
            t0 = time.perf_counter()
            try:
                status = httpx.get(url + path, params=params, headers=headers, timeout=30).status_code
            except httpx.HTTPError as exc:
                status = type(exc).__name__
            seen[path].append((status, time.perf_counter() - t0))
        stop.wait(PROBE_EVERY_S)


def idle_sockets(port: int, n: int, stop: threading.Event, counts: collections.Counter) -> None:
    """Hold ``n`` connections that never finish a request; reopen each one the server closes."""
    socks: list[socket.socket | None] = [None] * n
    try:
        while not stop.is_set():
            for k in range(n):
                s = socks[k]
                if s is not None and _open(s):
                    continue
                if s is not None:
                    s.close()
                    counts["closed_by_server"] += 1
                try:
                    s = socket.create_connection(("127.0.0.1", port), timeout=5)
                    if k % 2:
                        s.sendall(b"GET /heal")
                    s.setblocking(False)
                    socks[k] = s
                    counts["opened"] += 1
                except OSError:
                    socks[k] = None
                    counts["connect_failed"] += 1
            stop.wait(IDLE_CHECK_S)
    finally:
        for s in socks:
            if s is not None:
                s.close()


def _open(s: socket.socket) -> bool:
    """Whether the server still holds ``s`` open (what it sent before closing, a 408, is read away)."""
    try:
        while s.recv(4096):
            pass
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


async def streams(url: str, n: int, seconds: float, frames: collections.Counter, query: str) -> None:
    ws_url = url.replace("http://", "ws://") + "/stream" + query

    async def one(k: int) -> None:
        async with websockets.connect(ws_url, max_size=1 << 24) as ws:
            sub = {"mode": "live", "fps": 10} if k % 2 else {"mode": "sweep", "fps": 10, "loop": True}
            await ws.send(json.dumps(sub))
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                try:
                    message = protocol.unpack(await asyncio.wait_for(ws.recv(), 5))
                except TimeoutError:
                    continue
                frames[message["type"] if message["type"] != "error" else "error:" + message["error"]] += 1

    await asyncio.gather(*(one(k) for k in range(n)))


def _latency(samples: list) -> dict:
    seconds = sorted(s for _, s in samples)
    statuses = collections.Counter(str(status) for status, _ in samples)
    if not seconds:
        return {"count": 0}
    return {"count": len(seconds), "statuses": dict(statuses),
            "p50_ms": round(1e3 * seconds[len(seconds) // 2]),
            "p99_ms": round(1e3 * seconds[min(len(seconds) - 1, int(0.99 * len(seconds)))]),
            "max_ms": round(1e3 * seconds[-1])}


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=180)
    p.add_argument("--warmup", type=float, default=30)
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--streams", type=int, default=10)
    p.add_argument("--idle", type=int, default=0, help="connections that never finish a request")
    p.add_argument("--token", action="store_true", help="serve with EDMCGS_TOKEN (clients send it)")
    p.add_argument("--probe-limit-s", type=float, default=None, help="fail when a probe takes longer")
    args = p.parse_args()
    raise_fd_limit()
    folder = Path(tempfile.mkdtemp())
    rec, ckpt = build_scene(folder, width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=2000,
                            control_points=64)
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"],
                        env={"EDMCGS_TOKEN": TOKEN} if args.token else None)
    headers = {"Authorization": f"Bearer {TOKEN}"} if args.token else {}
    try:
        srv.wait_ready(TOKEN if args.token else None)
        deadline = time.monotonic() + 60  # until the replay covers the probe's time
        while httpx.get(srv.url + "/render", params={"t": "0.5"}, headers=headers,
                        timeout=30).status_code != 200:
            if time.monotonic() > deadline:
                raise RuntimeError("the scene never rendered t = 0.5 s")
            time.sleep(0.2)
        stop, lock = threading.Event(), threading.Lock()
        statuses: collections.Counter = collections.Counter()
        frames: collections.Counter = collections.Counter()
        idle: collections.Counter = collections.Counter()
        probes: dict[str, list] = {"/healthz": [], "/render": []}
        threads = [threading.Thread(target=http_client, args=(srv.url, headers, stop, statuses, lock, k),
                                    daemon=True) for k in range(args.clients)]
        threads.append(threading.Thread(target=idle_sockets, args=(srv.port, args.idle, stop, idle),
                                        daemon=True))
        threads.append(threading.Thread(target=probe, args=(srv.url, headers, stop, probes), daemon=True))
        for th in threads:
            th.start()
        query = f"?token={TOKEN}" if args.token else ""
        ws_thread = threading.Thread(target=lambda: asyncio.run(streams(srv.url, args.streams, args.seconds,
                                                                         frames, query)), daemon=True)
        ws_thread.start()
        time.sleep(args.warmup)
        rss0 = srv.rss_mb()
        samples = [rss0]
        end = time.monotonic() + args.seconds - args.warmup
        while time.monotonic() < end:
            time.sleep(10)
            samples.append(srv.rss_mb())
        stop.set()
        ws_thread.join(30)
        for th in threads:
            th.join(30)
        rss1 = srv.rss_mb()
        metrics = httpx.get(srv.url + "/metrics", headers=headers, timeout=10).text
        fivexx = sum(float(line.rsplit(" ", 1)[1]) for line in metrics.splitlines()
                     if line.startswith("edmcgs_http_requests_total") and 'code="5' in line)
        growth = (rss1 - rss0) / rss0
        probe_report = {path: _latency(s) for path, s in probes.items()}
        report = {"seconds": args.seconds, "clients": args.clients, "streams": args.streams,
                  "idle": args.idle, "token": args.token, "render_statuses": dict(statuses),
                  "stream_messages": dict(frames), "idle_sockets": dict(idle), "probes": probe_report,
                  "server_5xx": fivexx, "rss_after_warmup_mb": round(rss0, 1), "rss_end_mb": round(rss1, 1),
                  "rss_max_mb": round(max([*samples, rss1]), 1), "rss_growth": round(growth, 4)}
        print(json.dumps(report, indent=1))
        seen = [sample for s in probes.values() for sample in s]
        probes_ok = all(probes.values()) and all(status == 200 for status, _ in seen)
        if args.probe_limit_s is not None:
            probes_ok = probes_ok and all(t <= args.probe_limit_s for _, t in seen)
        ok = (statuses[503] == 0 and fivexx == 0 and not any(s >= 500 for s in statuses) and growth < 0.05
              and probes_ok)
        print("soak:", "PASS" if ok else "FAIL")
        return 0 if ok else 1
    finally:
        srv.stop()


if __name__ == "__main__":
    sys.exit(main())
