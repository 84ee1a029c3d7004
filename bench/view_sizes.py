"""What the viewer's "fit" size costs: GET /render of the bundled demo at the camera's size and at the
sizes a browser window asks for, through a real ``edmcgs-serve``.

    .venv/bin/python -m bench.view_sizes [--json PATH] [--instants N] [--size WxH ...]

Each instant is deformed once by an untimed tiny render (the deformed state is cached per instant),
then rendered at every size, the sizes in a rotating order so that none always goes first; JPEG, as
the viewer asks. ``render_ms`` is the server's own time (render and encoding), ``client_ms`` the
request's round trip. The machine is shared: the load average is printed with the table.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from bench.results import table, write_json
from harness.server import ServerProcess

SIZES = ((173, 130), (346, 260), (562, 423), (865, 650))
"""The demo camera's size, twice it, and 'fit' in windows about 1280x560 and 1000x760 wide."""


def _size(text: str) -> tuple[int, int]:
    w, _, h = text.partition("x")
    return int(w), int(h)


def measure(url: str, sizes, instants: int) -> dict:
    from edmcgs.clients.client import Client

    client_ms = {s: [] for s in sizes}
    render_ms = {s: [] for s in sizes}
    with Client(url, timeout=120) as client:
        duration = client.scene()["duration_s"]
        for w, h in sizes:  # warm-up: every size's first encode and buffers
            client.render(t=0.0, width=w, height=h, format="jpeg")
        for i, t in enumerate(np.linspace(0.05, duration - 0.05, instants)):
            client.render(t=float(t), width=8, height=6, format="jpeg")  # the deform, untimed
            k = i % len(sizes)
            for w, h in (*sizes[k:], *sizes[:k]):
                t0 = time.perf_counter()
                _, meta = client.render(t=float(t), width=w, height=h, format="jpeg")
                client_ms[(w, h)].append((time.perf_counter() - t0) * 1e3)
                render_ms[(w, h)].append(meta.render_ms)
    out = {}
    for w, h in sizes:
        out[f"render_ms_{w}x{h}"] = float(np.median(render_ms[(w, h)]))
        out[f"client_ms_{w}x{h}"] = float(np.median(client_ms[(w, h)]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--instants", type=int, default=12, help="instants of the demo rendered (default 12)")
    p.add_argument("--size", type=_size, action="append", help="WIDTHxHEIGHT (repeat; default: "
                   + ", ".join(f"{w}x{h}" for w, h in SIZES) + ")")
    args = p.parse_args(argv)
    sizes = tuple(args.size or SIZES)
    srv = ServerProcess([], env={"EDMCGS_MAX_WIDTH": "4096", "EDMCGS_MAX_HEIGHT": "4096"})
    try:
        srv.wait_ready(None)
        results = measure(srv.url, sizes, args.instants)
    finally:
        srv.stop()
    results["instants"] = args.instants
    results["load_average_1m"] = round(os.getloadavg()[0], 2)
    print(table(results, {}))
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
