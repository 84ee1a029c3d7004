"""Event-to-frame latency at the head of a running server with online anchors fitting.

    .venv/bin/python -m bench.online_latency --recording LONG.h5 --checkpoint SHORT.ckpt [--json PATH]

``edmcgs-serve --replay LONG --checkpoint SHORT`` at real time; a websocket in live mode at 10 fps;
for each frame past the checkpoint's span, the latency is the client's receive time minus
``arrived_unix_us`` (when the oldest event new to that frame reached the ring), and its age the receive
time minus ``head_arrived_unix_us`` (when the batch that brought its time did), with the fit thread
correcting every anchor it can meanwhile; and the server's mean time per render stage (GET /metrics'
``edmcgs_render_stage_seconds``: the projection onto the events is the ``project`` stage).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.results import table, write_json
from harness.server import ServerProcess, metric_values


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--recording", type=Path, required=True)
    p.add_argument("--checkpoint", type=Path, required=True)
    p.add_argument("--seconds", type=float, default=4.0, help="stream time past the span measured")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    from edmcgs.clients.client import Client

    srv = ServerProcess(["--replay", str(args.recording), "--checkpoint", str(args.checkpoint)])
    try:
        srv.wait_ready()
        with Client(srv.url, timeout=30) as client:
            end = client.scene()["t_end_us"]
            lat, ages, kinds, projected = [], [], {}, 0
            with client.stream({"mode": "live", "fps": 10, "format": "jpeg"}) as stream:
                deadline = time.monotonic() + 120
                for frame in stream:
                    now = time.time_ns() // 1000
                    if frame.t_us > end and frame.arrived_unix_us is not None:
                        lat.append((now - frame.arrived_unix_us) / 1e3)
                        ages.append((now - frame.head_arrived_unix_us) / 1e3)
                        kinds[frame.anchor] = kinds.get(frame.anchor, 0) + 1
                        projected += bool(frame.projected)
                    if frame.t_us > end + args.seconds * 1e6 or time.monotonic() > deadline:
                        break
            online = client.scene()["online"]
            values = metric_values(client.metrics())
    finally:
        srv.stop()
        problems = [line for line in srv.log().splitlines() if "Error" in line or "failed" in line]
        if problems:
            print("server log:", *problems[-10:], sep="\n  ")
    results = {"frames": len(lat), "latency_p50_ms": float(np.median(lat)),
               "latency_p90_ms": float(np.percentile(lat, 90)), "frame_age_p50_ms": float(np.median(ages)),
               "frame_age_p90_ms": float(np.percentile(ages, 90)), "anchor_kinds": kinds,
               "online_predicted": online["predicted"], "online_corrected": online["corrected"],
               "online_skipped": online["skipped"]["superseded"], "fit_median_s": online["fit"]["median_s"],
               "fit_last_s": online["fit"]["last_s"], "queue_depth": online["queue_depth"],
               "frames_projected": projected}
    for stage in ("state", "raster", "project", "encode"):  # the mean over every render of the run
        key = f'edmcgs_render_stage_seconds_{{}}{{{{stage="{stage}"}}}}'
        count = values.get(key.format("count"), 0)
        results[f"{stage}_mean_ms"] = 1e3 * values[key.format("sum")] / count if count else None
    print(table(results, {}))
    print("anchor kinds of the frames:", kinds)
    write_json(args.json, results)


if __name__ == "__main__":
    main()
