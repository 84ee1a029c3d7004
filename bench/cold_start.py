"""A cold start as a user lives it: a recording replayed in real time through ``edmcgs-serve --replay REC``
with no checkpoint, every held-out frame's live render scored against wall-clock time since start.

    .venv/bin/python -m bench.cold_start --recording traffic.h5 [--minutes 12] [--every 20]
        [--offline CACHE] [--json PATH] [--csv PATH] [--plot PATH]

The server replays the recording's anchor frames (what a camera at the anchor rate gives) and its
events; its ``held_out`` frames are the ground truth. Every ``--every`` seconds each held-out time is
rendered by the running service (``GET /render?t_us=...``, the event camera's own view) and scored
(PSNR over all pixels, and over the moving ones as ``bench.online`` counts them) beside what needs no
model, on the same frames: hold the last frame, the events integrated onto it, that frame projected into
the bounds the events put on each pixel, and (not causal) the blend of the frames either side. By 1 s
band of scene time, the live render against the events integrated, at each round.

Also measured: the first render after the first frame reached the server, when the first learnt model
went live (from the first anchor), ``GET /render`` latency while the learner runs, the websocket's frame
rate, the learner's CPU (these three once the load below is over). For ``--load-minutes`` from the start,
4 clients render the head and 2 live streams run: around each model swap (5 s either side), the failed
requests, the p99 latency and every stream reset. With ``--offline CACHE``: the recording trained
offline by ``edmcgs train --config real`` (``--offline-preset``; bench.traffic's cached run, one thread) on
what the service was sent; when the recording has no poses, with ``--poses auto`` over the anchor frames
(``sent``: the held-out frames are never sent), and beside it the same run with structure from motion over
every frame (what a camera sending every frame would give). At the end the learner's saved model and the
offline ones are scored on the held-out frames by the same code (``bench.traffic.score``; without poses,
each from its own trajectory), with the learner's CPU seconds beside the offline run's; and the first model
the learner published once it had spent the offline run's CPU seconds (copied when the service said it
went live), scored the same way: the target's comparison, at equal CPU.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.online import MOVING, _psnr
from bench.results import table, write_json

TARGETS = {"first_render_s": ("<=", 2.0), "first_model_s": ("<=", 60.0), "render_p50_ms": ("<=", 15.0),
           "stream_fps": (">=", 30.0), "live_minus_integrate_worst_band_db": (">=", 0.0),
           "live_minus_integrate_worst_band_moving_db": (">=", 0.0),
           "learnt_minus_offline_db": (">=", -0.5), "swap_failed_requests": ("<=", 0),
           "swap_stream_resets": ("<=", 0), "swap_p99_ms": ("<=", 150.0)}
BASELINES = ("hold_last", "integrate", "hold_projected", "blend")
TIE_DB = 1e-6
"""Band differences smaller than this are 0: before any model (and past a moving camera's poses) the live
render is the same integration as the baseline, scored through other float32 arithmetic (-1e-7 dB seen)."""


def _tied(db: float) -> float:
    return 0.0 if abs(db) < TIE_DB else db


def baselines(rec) -> tuple[list[dict], np.ndarray]:
    """Per held-out frame: its time, truth, moving mask and the no-model renders (``BASELINES``)."""
    from edmcgs.model.eval.baselines import DEFAULT_CONTRAST
    from edmcgs.model.online.bounds import integrate, project
    from edmcgs.sensor.event_map import accumulate

    contrast = DEFAULT_CONTRAST if rec.contrast_threshold is None else rec.contrast_threshold
    anchor_t = rec.anchors.t_us
    still = np.median(rec.anchors.images, axis=0) / 255.0
    frames = []
    for j in range(len(rec.held_out)):
        t = int(rec.held_out.t_us[j])
        k = int(np.searchsorted(anchor_t, t, side="right")) - 1
        if k < 0:
            continue
        truth = rec.held_out.images[j] / 255.0
        frame = rec.anchors.images[k] / 255.0
        events = accumulate(rec.events.time_slice(int(anchor_t[k]), t), rec.width, rec.height)
        images = {"hold_last": frame, "integrate": integrate(frame, events, contrast),
                  "hold_projected": project(frame, frame, events, contrast)}
        if k + 1 < len(anchor_t):
            w = (t - int(anchor_t[k])) / float(anchor_t[k + 1] - anchor_t[k])
            images["blend"] = (1 - w) * frame + w * rec.anchors.images[k + 1] / 255.0
        moving = np.abs(truth - still).max(-1) > MOVING
        scores = {}
        for name, image in images.items():
            image = np.round(np.clip(image, 0, 1) * 255) / 255  # in the 8 bits the service delivers
            scores[name] = _psnr(image, truth)
            scores[f"{name}_moving"] = _psnr(image[moving], truth[moving]) if moving.any() else None
        frames.append({"t_us": t, "truth": truth, "moving": moving, "scores": scores})
    return frames, still


def score_round(client, frames: list[dict], started: float, head_us: int) -> list[dict]:
    """Every held-out frame the stream has reached (``head_us``) rendered by the service now and scored,
    beside its baselines."""
    rows = []
    for f in frames:
        if f["t_us"] > head_us:
            break
        t0 = time.perf_counter()
        image, meta = client.render(t_us=f["t_us"], format="msgpack")
        latency_ms = (time.perf_counter() - t0) * 1e3
        image = image / 255.0
        m = f["moving"]
        rows.append({"wall_s": time.monotonic() - started, "t_us": f["t_us"], "model": meta.model_version,
                     "anchor": meta.anchor, "latency_ms": latency_ms, "render_ms": meta.render_ms,
                     "live": _psnr(image, f["truth"]),
                     "live_moving": _psnr(image[m], f["truth"][m]) if m.any() else None, **f["scores"]})
    return rows


def bands(rows: list[dict], origin_us: int, width_s: float = 1.0) -> list[dict]:
    """Per 1 s band of scene time: the mean live and integrated PSNR (all and moving pixels)."""
    out = []
    index = np.array([(r["t_us"] - origin_us) // int(width_s * 1e6) for r in rows])
    for k in np.unique(index):
        sel = [r for r, i in zip(rows, index, strict=True) if i == k]
        band = {"from_s": float(k * width_s), "frames": len(sel)}
        for name in ("live", "integrate"):
            band[name] = float(np.mean([r[name] for r in sel]))
            moving = [r[f"{name}_moving"] for r in sel if r[f"{name}_moving"] is not None]
            band[f"{name}_moving"] = float(np.mean(moving)) if moving else None
        out.append(band)
    return out


def stream_fps(url: str, seconds: float = 5.0) -> float:
    """Frames per second a websocket delivers sweeping the renderable span at 60 fps in a loop (a sweep
    renders every frame, where a live stream waits for the head)."""
    from edmcgs.clients.client import Client

    with Client(url) as client, client.stream({"mode": "sweep", "t0": 0.0, "fps": 60, "loop": True,
                                               "format": "jpeg"}) as stream:
        first = stream.receive(timeout=30)
        n, t0 = 0, time.monotonic()
        while first is not None and time.monotonic() - t0 < seconds:
            if stream.receive(timeout=5) is not None:
                n += 1
        return n / max(time.monotonic() - t0, 1e-9)


class Load:
    """What viewers put on the service while models are swapped in: ``clients`` threads rendering the
    camera's view at the head in a loop and ``streams`` live websockets, for ``seconds``. Every request's
    wall time, latency and outcome is kept. The streams sweep the renderable span in a loop (a live one
    ends with the replay): one that errs or closes before the end is a reset, and the model versions
    each one saw tell that it lived through the swaps."""

    def __init__(self, url: str, seconds: float, clients: int = 4, streams: int = 2):
        self.url, self.stop_at = url, time.time() + seconds
        self.requests: list[tuple[float, float, bool]] = []  # (unix time, latency ms, ok)
        self.resets: list[str] = []
        self.frames = 0
        self.versions: list[set] = []  # per stream, the model versions its frames came from
        self.threads = [threading.Thread(target=self._render, daemon=True) for _ in range(clients)]
        self.threads += [threading.Thread(target=self._stream, daemon=True) for _ in range(streams)]
        for th in self.threads:
            th.start()

    def _render(self) -> None:
        from edmcgs.clients.client import Client

        with Client(self.url, timeout=30) as client:
            while (now := time.time()) < self.stop_at:
                t0 = time.perf_counter()
                try:
                    client.render(format="jpeg")
                    ok = True
                except Exception:  # a failed request is what this counts
                    ok = False
                self.requests.append((now, (time.perf_counter() - t0) * 1e3, ok))

    def _stream(self) -> None:
        from edmcgs.clients.client import Client

        seen: set = set()
        self.versions.append(seen)
        try:
            with Client(self.url, timeout=30) as client, \
                    client.stream({"mode": "sweep", "t0": 0.0, "fps": 30, "loop": True,
                                   "format": "jpeg"}) as stream:
                while time.time() < self.stop_at:
                    frame = stream.receive(timeout=30)
                    if frame is None:
                        self.resets.append("closed by the server")
                        return
                    seen.add(frame.model_version)
                    self.frames += 1
        except Exception as exc:  # a reset is what this counts
            self.resets.append(f"{type(exc).__name__}: {exc}")

    def join(self) -> None:
        for th in self.threads:
            th.join(timeout=60)

    def around(self, swaps_unix: list[float], margin_s: float = 5.0) -> dict:
        """Requests within ``margin_s`` of a swap: how many, how many failed, their p99; and every
        stream reset of the whole load."""
        near = [r for r in self.requests if any(abs(r[0] - s) <= margin_s for s in swaps_unix)]
        latencies = [ms for _, ms, ok in near if ok]
        return {"swap_requests": len(near), "swap_failed_requests": sum(not ok for _, _, ok in near),
                "swap_p99_ms": float(np.percentile(latencies, 99)) if latencies else None,
                "swap_stream_resets": len(self.resets), "swap_stream_frames": self.frames,
                "swap_stream_versions": [sorted(v, key=lambda x: -1 if x is None else x)
                                         for v in self.versions],
                "swaps_under_load": sum(s <= self.stop_at for s in swaps_unix),
                "load_requests": len(self.requests),
                "load_failed_requests": sum(not ok for _, _, ok in self.requests)}


def run(rec_path: Path, minutes: float, every: float, workdir: Path, env: dict, load_s: float = 0.0,
        snapshot: tuple[float, Path] | None = None) -> dict:
    """snapshot: (CPU seconds, path): the first model published once the learner had spent them is
    copied there (the learner keeps its two newest checkpoints: each poll sees the newest)."""
    from edmcgs.clients.client import Client
    from edmcgs.sensor.files.recording import read_recording
    from harness.server import ServerProcess

    rec = read_recording(rec_path)
    frames, _ = baselines(rec)
    first_frame_s = (int(rec.anchors.t_us[0]) - rec.t_range_us[0]) / 1e6
    # the ring holds the whole recording: every held-out frame stays renderable from its events (a moving
    # camera's street fires more events than the default ring keeps)
    env = {"EDMCGS_RING_EVENTS": str(max(4_000_000, int(len(rec.events) * 1.1)))} | env
    srv = ServerProcess(["--replay", str(rec_path), "--learn-dir", str(workdir)], env=env)
    rows, models, rounds, load, snapped = [], {}, [], None, None
    try:
        srv.wait_ready()
        started, started_unix = time.monotonic(), time.time()  # the replay started with the service
        with Client(srv.url) as client:
            while True:  # the first render of the camera's view after the first frame arrived
                try:
                    client.render(format="msgpack")
                    break
                except Exception:
                    time.sleep(0.02)
            first_render_s = max(0.0, time.monotonic() - started - first_frame_s)
            load = Load(srv.url, load_s) if load_s > 0 else None
            fps = None  # measured once a model is live, while the learner goes on
            deadline = started + minutes * 60
            while time.monotonic() < deadline:
                tick = time.monotonic()
                scene = client.scene()
                learning = scene["learning"]
                if learning["model"] is not None:
                    model = models.setdefault(learning["model"]["version"], learning["model"])
                    if snapshot is not None and snapped is None and model["cpu_s"] >= snapshot[0]:
                        shutil.copyfile(workdir / f"learned-{model['version']:04d}.ckpt", snapshot[1])
                        snapped = model
                    if fps is None and (load is None or time.time() > load.stop_at):
                        fps = stream_fps(srv.url)
                batch = score_round(client, frames, started, scene["head_us"] or 0)
                if batch:
                    for row in batch:
                        row["round"] = len(rounds)
                    rows += batch
                    rounds.append({"wall_s": batch[0]["wall_s"], "model": batch[0]["model"],
                                   "learnt": learning["model"],
                                   "bands": bands(batch, int(rec.anchors.t_us[0]))})
                    print(f"{rounds[-1]['wall_s']:7.1f} s  model {batch[0]['model']}: live "
                          f"{np.mean([r['live'] for r in batch]):.2f} dB, integrate "
                          f"{np.mean([r['integrate'] for r in batch]):.2f}", file=sys.stderr)
                time.sleep(max(0.0, every - (time.monotonic() - tick)))
    finally:
        if load is not None:
            load.join()
        srv.stop(signal.SIGINT, timeout=300)
    first_model = min(models.values(), key=lambda m: m["version"], default=None)
    swaps = load.around([m["live_unix"] for m in models.values()]) if load is not None else {}
    return swaps | {"rows": rows, "rounds": rounds,
                    "models": sorted(models.values(), key=lambda m: m["version"]),
            "first_render_s": first_render_s, "stream_fps": fps,
            "first_model_s": None if first_model is None else
            first_model["live_unix"] - started_unix - first_frame_s,
            "render_p50_ms": float(np.median(quiet)) if (quiet := [
                r["latency_ms"] for r in rows
                if load is None or started_unix + r["wall_s"] > load.stop_at]) else None,
            "snapshot": snapped, "log": srv.log()}


def _has_poses(rec_path: Path) -> bool:
    from edmcgs.pipeline import open_recording

    rec = open_recording(rec_path, lazy_events=True)
    return rec.trajectory_t_us is not None or rec.anchors.poses is not None


def offline_run(rec_path: Path, cache: Path, preset: str, estimated: bool) -> dict:
    """The offline run of the recording with ``preset`` (cached): on its poses, else (``estimated``) on
    those structure from motion finds (``--poses auto``) over the frames the service was sent, as the
    learner's are: a copy of the recording with its anchors alone (``sent``)."""
    from bench.traffic import train

    if not estimated:
        return train(rec_path, "offline", [], cache, preset)
    return train(sent(rec_path, cache), "offline", [], cache, preset, poses="auto")


def every_frame_run(rec_path: Path, cache: Path, preset: str) -> dict:
    """The same offline run with structure from motion over every frame of the recording, held-out ones
    included: what a camera that sent every frame would give the learner (the replay sends anchors)."""
    from bench.traffic import train

    return train(rec_path, "offline, poses from every frame", [], cache, preset, poses="auto")


def sent(rec_path: Path, cache: Path) -> Path:
    """A copy of the recording (in ``cache``) with what its replay sends the service: the events, the
    anchor frames and the camera; no held-out frames, novel views or IMU."""
    from dataclasses import replace

    from edmcgs.sensor.files.recording import read_recording, write_recording

    path = cache / f"{rec_path.stem}_sent.h5"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        rec = read_recording(rec_path)
        write_recording(path, replace(rec, held_out=None, novel_views=None, imu=None))
    return path


def offline(rec_path: Path, cache: Path, runs: dict[str, dict], learnt: dict[str, Path],
            estimated: bool) -> dict:
    """Each offline run in ``runs`` ({name: bench.traffic.train's result}) and each ``learnt`` model scored
    on the held-out frames by the same code; without poses in the recording, each model renders them from
    its own estimated trajectory (its own world frame), as the service renders it."""
    from bench.traffic import score
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.pipeline import open_recording, training_data

    data = training_data(open_recording(rec_path))
    models = {name: load_checkpoint(cache / info["checkpoint"]) for name, info in runs.items()} | \
        {name: load_checkpoint(path) for name, path in learnt.items()}
    return {"runs": runs, "scores": score(data, models, static_camera=not estimated, own_poses=estimated)[0]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.cold_start", description=__doc__.split("\n\n")[0])
    p.add_argument("--recording", type=Path, required=True)
    p.add_argument("--minutes", type=float, default=12.0, help="how long the service runs (default 12)")
    p.add_argument("--every", type=float, default=20.0, help="seconds between scoring rounds (default 20)")
    p.add_argument("--preset", default="auto", help="the config the learner trains (default auto: moving for "
                   "a camera that translates, else real)")
    p.add_argument("--load-minutes", type=float, default=3.0,
                   help="4 render clients and 2 live streams on the service for its first minutes, so that "
                        "the first swaps happen under load (default 3; 0: none)")
    p.add_argument("--offline", type=Path, metavar="CACHE",
                   help="also train offline (cached here) and compare")
    p.add_argument("--offline-preset", default="real",
                   help="the offline run's config (default real; moving for a camera that translates)")
    p.add_argument("--keep", type=Path, metavar="DIR",
                   help="keep the learner's checkpoints here (its saved one and, with --offline, the one at "
                        "equal CPU)")
    p.add_argument("--json", type=Path)
    p.add_argument("--csv", type=Path, help="every scored render")
    p.add_argument("--plot", type=Path, help="PSNR against wall-clock time since start (PNG)")
    args = p.parse_args(argv)
    env = {"EDMCGS_LEARN_PRESET": args.preset}
    with tempfile.TemporaryDirectory() as tmp:
        workdir, equal = Path(tmp) / "learnt", Path(tmp) / "equal-cpu.ckpt"
        estimated = args.offline is not None and not _has_poses(args.recording)
        run_info = None if args.offline is None else \
            offline_run(args.recording, args.offline, args.offline_preset, estimated)
        snapshot = None if run_info is None else (run_info["cpu_s"], equal)
        r = run(args.recording, args.minutes, args.every, workdir, env, args.load_minutes * 60, snapshot)
        results = {k: v for k, v in r.items() if k not in ("rows", "log")}
        last = r["rounds"][-1]["bands"] if r["rounds"] else []
        every_band = [b for rnd in r["rounds"] for b in rnd["bands"]]
        if every_band:
            results["live_minus_integrate_worst_band_db"] = _tied(min(b["live"] - b["integrate"]
                                                                      for b in every_band))
            moving = [b["live_moving"] - b["integrate_moving"] for b in every_band
                      if b["live_moving"] is not None and b["integrate_moving"] is not None]
            results["live_minus_integrate_worst_band_moving_db"] = _tied(min(moving)) if moving else None
            results["last_round_bands"] = last
        if args.offline is not None:
            saved = workdir / "learned.ckpt"
            if not saved.is_file():
                raise SystemExit(f"the learner saved no checkpoint; its log:\n{r['log'][-4000:]}")
            learnt = {"learnt": saved} | ({"learnt at equal CPU": equal} if equal.is_file() else {})
            runs = {"offline": run_info} | ({"offline, poses from every frame": every_frame_run(
                args.recording, args.offline, args.offline_preset)} if estimated else {})
            results["offline"] = offline(args.recording, args.offline, runs, learnt, estimated)
            s = results["offline"]["scores"]
            results["learnt_final_minus_offline_db"] = s["learnt"]["psnr"] - s["offline"]["psnr"]
            results["learner_cpu_s"] = r["models"][-1]["cpu_s"] if r["models"] else None
            results["offline_cpu_s"] = run_info["cpu_s"]
            if r["snapshot"] is not None:  # the target: once the learner has spent the offline run's CPU
                results["learnt_minus_offline_db"] = s["learnt at equal CPU"]["psnr"] - s["offline"]["psnr"]
                results["equal_cpu_model"] = r["snapshot"]
        if args.keep is not None:
            args.keep.mkdir(parents=True, exist_ok=True)
            for kept in (workdir / "learned.ckpt", equal):
                if kept.is_file():
                    shutil.copyfile(kept, args.keep / kept.name)
    if args.csv is not None and r["rows"]:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(r["rows"][0]))
            w.writeheader()
            w.writerows(r["rows"])
    if args.plot is not None and r["rows"]:
        plot(r["rows"], args.plot)
    write_json(args.json, results | {"targets": TARGETS})
    print(table(results, TARGETS))
    print(json.dumps({k: results[k] for k in ("models",) if k in results}, indent=1)[:2000])
    return 0


def plot(rows: list[dict], path: Path) -> None:
    """Mean PSNR of each scoring round against wall-clock time, beside the no-model renders: over all
    pixels and over the moving ones; a dashed line where the first learnt model went live."""
    from matplotlib.figure import Figure

    from bench.figures import save

    rounds = sorted({r["round"] for r in rows})
    walls = [min(r["wall_s"] for r in rows if r["round"] == k) for k in rounds]
    learnt = [r["wall_s"] for r in rows if r["model"] is not None]
    fig = Figure(figsize=(10, 4.2), layout="constrained")
    for ax, suffix, title in zip(fig.subplots(1, 2), ("", "_moving"), ("all pixels", "moving pixels"),
                                 strict=True):
        for key, label, colour in (("live", "live render (cold start)", "#1b6ca8"),
                                   ("integrate", "events integrated onto the last frame", "#66a182"),
                                   ("hold_projected", "last frame projected onto the events", "#c2a83e"),
                                   ("hold_last", "hold the last frame", "#888888")):
            means = [np.mean([v for r in rows if r["round"] == k and (v := r[key + suffix]) is not None])
                     for k in rounds]
            ax.plot(walls, means, marker="o", ms=3, color=colour, label=label)
        if learnt:
            ax.axvline(min(learnt), color="#1b6ca8", ls="--", lw=0.8)
        ax.set_title(f"{title} (dashed: the first learnt model live)", fontsize=9)
        ax.set_xlabel("wall-clock time since the service started (s)")
        ax.grid(alpha=0.3)
    fig.axes[0].set_ylabel("mean PSNR over the held-out frames reached (dB)")
    fig.axes[0].legend(fontsize=8, loc="center right")
    path.parent.mkdir(parents=True, exist_ok=True)
    save(fig, path)


if __name__ == "__main__":
    sys.exit(main())
