"""Hostile websocket clients against a real ``edmcgs-serve`` (the bundled demo scene, default settings),
in two rounds: ``max_streams`` (16) connections that never subscribe; then as many that subscribe at
60 fps and then read nothing (raw sockets: no pong either). Measured per round: when a new viewer is
served again, and what the server spends on them once their slots are back.

    .venv/bin/python -m bench.hostile [--json PATH]

Keys (targets; ``unsubscribed_*`` and ``stalled_*`` alike):
    *_slots_back_s        the hostile clients connected -> a new viewer gets ``subscribed``
                          (not ``busy``)                                                    <= 10
    *_cores               server CPU (cores) over the next 10 s, less its CPU without them
                          (the replay's ingest) measured before                            <= 0.05
    *_renders_after       stream renders over those 10 s (no viewer subscribed)             <= 0
    stalled_renders       stream renders for the ones that read nothing, all told
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import socket
import sys
import time

import httpx
from websockets.sync.client import connect

from bench.results import table, write_json
from edmcgs import protocol
from harness.server import ServerProcess, metric_values

TARGETS = {f"{name}_{key}": target for name in ("unsubscribed", "stalled")
           for key, target in (("slots_back_s", ("<=", 10.0)), ("cores", ("<=", 0.05)),
                               ("renders_after", ("<=", 0)))}
RENDERS = 'edmcgs_render_seconds_count{path="stream"}'
SUBSCRIPTION = {"mode": "sweep", "fps": 60, "loop": True, "format": "jpeg"}
WINDOW_S = 10.0


def silent_websocket(port: int, subscription: dict | None) -> socket.socket:
    """A websocket that completes its handshake, sends ``subscription`` (if any), then reads nothing."""
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(f"GET /stream HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    if not head.startswith(b"HTTP/1.1 101"):
        raise RuntimeError(f"no websocket: {head[:80]!r}")
    if subscription is not None:
        payload, mask = json.dumps(subscription).encode(), os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        s.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)
    return s


def first_message(port: int) -> str:
    """What a new viewer is told first: ``subscribed``, or the error (``busy``)."""
    try:
        with connect(f"ws://127.0.0.1:{port}/stream", open_timeout=10) as ws:
            ws.send(json.dumps(SUBSCRIPTION))
            message = protocol.unpack(ws.recv(timeout=10))
    except Exception as exc:  # closed before an answer
        return type(exc).__name__
    return message["type"] if message["type"] != "error" else message["error"]


def measure(srv: ServerProcess, name: str, hostile_count: int, subscription: dict | None) -> dict:
    def renders() -> float:
        return metric_values(httpx.get(srv.url + "/metrics", timeout=10).text).get(RENDERS, 0.0)

    cpu0, t0 = srv.cpu_s(), time.monotonic()
    time.sleep(WINDOW_S)
    baseline = (srv.cpu_s() - cpu0) / (time.monotonic() - t0)
    start, renders0 = time.monotonic(), renders()
    hostile = [silent_websocket(srv.port, subscription) for _ in range(hostile_count)]
    try:
        while (answer := first_message(srv.port)) != "subscribed":
            if time.monotonic() - start > 60:
                raise RuntimeError(f"no slot after 60 s (last answer: {answer})")
            time.sleep(0.2)
        slots_back = time.monotonic() - start
        renders1 = renders()
        cpu1, t1 = srv.cpu_s(), time.monotonic()
        time.sleep(WINDOW_S)
        cores = (srv.cpu_s() - cpu1) / (time.monotonic() - t1)
        renders2 = renders()
    finally:
        for s in hostile:
            s.close()
    out = {f"{name}_slots_back_s": round(slots_back, 2), f"{name}_baseline_cores": round(baseline, 3),
           f"{name}_cores_after": round(cores, 3), f"{name}_cores": round(max(0.0, cores - baseline), 3),
           f"{name}_renders_after": int(renders2 - renders1)}
    if subscription is not None:  # the new viewers asking for a slot render a frame or so each, too
        out[f"{name}_renders"] = int(renders1 - renders0)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.hostile", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=str, default=None)
    args = p.parse_args(argv)
    srv = ServerProcess([])
    try:
        srv.wait_ready()
        slots = 16  # the default max_streams
        results = measure(srv, "unsubscribed", slots, None) | measure(srv, "stalled", slots, SUBSCRIPTION)
    finally:
        srv.stop()
    print(table(results, TARGETS))
    write_json(args.json, {"results": results, "targets": TARGETS})
    return 0


if __name__ == "__main__":
    sys.exit(main())
