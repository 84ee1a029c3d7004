"""Soak: 4 HTTP clients rendering in a loop and 10 websocket streams against one edmcgs-serve, for a
while; reports every status seen, the 503s, the 5xx and the server's RSS growth after warm-up.

    .venv/bin/python scripts/soak.py [--seconds 180] [--warmup 30] [--clients 4] [--streams 10]

Exits non-zero when a /render answered 503 or anything answered 5xx, or RSS grew 5 % or more after
the warm-up. The scene is the tests' tiny synthetic one (tests.support.server.build_scene).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import httpx
import websockets

from edmcgs import protocol
from tests.support.server import HEIGHT, WIDTH, ServerProcess, build_scene


def http_client(url: str, stop: threading.Event, statuses: collections.Counter, lock: threading.Lock,
                k: int) -> None:
    with httpx.Client(base_url=url, timeout=30) as c:
        i = 0
        while not stop.is_set():
            t = 0.05 + (i * 0.173 + k * 0.31) % 1.9
            r = c.get("/render", params={"t": f"{t:.3f}", "format": "jpeg" if i % 2 else "png"})
            with lock:
                statuses[r.status_code] += 1
            i += 1


async def streams(url: str, n: int, seconds: float, frames: collections.Counter) -> None:
    ws_url = url.replace("http://", "ws://") + "/stream"

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


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=180)
    p.add_argument("--warmup", type=float, default=30)
    p.add_argument("--clients", type=int, default=4)
    p.add_argument("--streams", type=int, default=10)
    args = p.parse_args()
    folder = Path(tempfile.mkdtemp())
    rec, ckpt = build_scene(folder, width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=2000,
                            control_points=64)
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"])
    try:
        srv.wait_ready()
        stop, lock = threading.Event(), threading.Lock()
        statuses: collections.Counter = collections.Counter()
        frames: collections.Counter = collections.Counter()
        threads = [threading.Thread(target=http_client, args=(srv.url, stop, statuses, lock, k), daemon=True)
                   for k in range(args.clients)]
        for th in threads:
            th.start()
        ws_thread = threading.Thread(target=lambda: asyncio.run(streams(srv.url, args.streams,
                                                                         args.seconds, frames)), daemon=True)
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
        metrics = httpx.get(srv.url + "/metrics", timeout=10).text
        fivexx = sum(float(line.rsplit(" ", 1)[1]) for line in metrics.splitlines()
                     if line.startswith("edmcgs_http_requests_total") and 'code="5' in line)
        growth = (rss1 - rss0) / rss0
        report = {"seconds": args.seconds, "clients": args.clients, "streams": args.streams,
                  "render_statuses": dict(statuses), "stream_messages": dict(frames),
                  "server_5xx": fivexx, "rss_after_warmup_mb": round(rss0, 1), "rss_end_mb": round(rss1, 1),
                  "rss_max_mb": round(max([*samples, rss1]), 1), "rss_growth": round(growth, 4)}
        print(json.dumps(report, indent=1))
        ok = statuses[503] == 0 and fivexx == 0 and not any(s >= 500 for s in statuses) and growth < 0.05
        print("soak:", "PASS" if ok else "FAIL")
        return 0 if ok else 1
    finally:
        srv.stop()


if __name__ == "__main__":
    sys.exit(main())
