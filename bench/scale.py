"""The scale benchmark: how training, memory, the checkpoint, quality and serving grow with a recording.

    .venv/bin/python -m bench.scale [--scenes traffic,street3d] [--lengths 3,10,30,60]
        [--only build,train,score,serve,events,ray] [--out reports] [--cache reports/cache/scale]

1. Builds each scene at each length, anchors at 5 fps (``edmcgs synth SCENE --fps 5 --seconds S --seed 0``:
   346x260 grey APS frames at 25 Hz, DAVIS346-like events; the frames between anchors held out).
2. Trains each with ``edmcgs train REC --config PRESET --threads 1`` in its own process and measures that
   process: wall and CPU time, peak resident memory; then the checkpoint's size and Gaussians. traffic's
   static camera trains with ``real`` (100 steps per span between anchors); street3d's handheld one
   with ``moving`` (75 steps per span), on the poses a user would have: ``edmcgs record REC --poses
   auto`` first (``bench.street3d.estimate``: structure from motion with the IMU, its time and its
   trajectory error reported).
3. Scores each checkpoint on every held-out frame beside the three baselines (hold the last anchor,
   blend the neighbouring anchors, integrate the events onto the last anchor: ``model/eval/baselines``).
4. Serves each (``edmcgs-serve --replay REC --checkpoint CKPT --loop --speed 4``): GET /render p50, one
   client, a new time each request (``bench.serve.measure_single``), in rounds that alternate the lengths
   (the machine is shared: a length's median over the rounds), and the server's resident memory.
5. The event path alone over 10 minutes: the 10 s traffic recording tiled to 600 s, replayed as fast
   as it reads through the HDF5 replay into the server's ring (4 M events), I_E of a 50 ms window taken
   from the ring as it fills; the peak resident memory of that process.
6. Data-parallel: ``edmcgs train --ray --workers 1`` against ``--workers 2`` on the shortest traffic
   recording: wall time and held-out PSNR.

Every step is cached in ``--cache`` by what determines it (recordings by their arguments, runs by the
recording and the resolved config, scores and serving by the checkpoint): an interrupted run resumes
(a training from its last mid-training checkpoint, ``edmcgs train --resume``),
and a long training can run alone (``--only train --lengths 60``) while the rest is read from the cache.
A length repeated trains again, cached apart: ``--lengths 3,60,3`` in a fresh cache runs the lengths
alternately in one session, and the 60 s / 3 s ratios take the mean of the 3 s runs.
Writes ``scale.md`` and ``bench/scale.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import re
import resource
import sys
import time
from pathlib import Path

import numpy as np

from bench.results import meets, table, write_json
from bench.traffic import _edmcgs, measured_run

SCENES = ("traffic", "street3d")
PRESETS = {"traffic": "real", "street3d": "moving"}
"""Each scene's ``--config``: the static street camera's preset, and the handheld camera's."""
LENGTHS = (3, 10, 30, 60)
FPS = 5
EVENT_PATH_S = 600
"""The event path's recording: 10 minutes ..."""
EVENT_SOURCE_S = 10
"""... of the 10 s traffic recording's events, tiled."""
EVENT_WINDOW_US = 50_000
TARGETS = {
    "traffic_margin_db_min": (">=", 1.0),
    "street3d_margin_db_min": (">=", 1.0),
    "traffic_cpu_per_s_ratio_60_3": ("<=", 1.2),
    "traffic_train_peak_gb_60": ("<=", 4.0),
    "event_path_peak_gb_600s": ("<=", 1.0),
    "traffic_render_p50_ratio_60_3": ("<=", 1.2),
    "ray_psnr_diff_db": ("<=", 0.2),
}
STEPS = ("build", "train", "score", "serve", "events", "ray")


def _digest(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _cached(path: Path, make) -> dict:
    """``make()``'s JSON, kept at ``path`` (written atomically: an interrupted run leaves none)."""
    if path.exists():
        return json.loads(path.read_text())
    out = make()
    tmp = path.with_suffix(".partial")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(path)
    return out


# ------------------------------------------------------------------------------- 1. recordings

SIZES = {"full": (346, 260), "small": (173, 130)}
"""``edmcgs synth --size``: the DAVIS346's resolution, or half of it (a quarter of the cost)."""


def recording_path(cache: Path, scene: str, seconds: int, size: str = "full") -> Path:
    return cache / (f"{scene}_fps{FPS}_s{seconds}_seed0.h5" if size == "full" else
                    f"{scene}_{size}_fps{FPS}_s{seconds}_seed0.h5")


def recording(cache: Path, scene: str, seconds: int, size: str = "full") -> Path:
    """The scene at ``seconds`` (built once)."""
    path = recording_path(cache, scene, seconds, size)
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".partial.h5")
        print(f"building {path.name} ...", file=sys.stderr)
        usage = measured_run([*_edmcgs(), "synth", scene, "--fps", str(FPS), "--seconds", str(seconds),
                              "--seed", "0", "--size", size, "-q", "-o", str(tmp)],
                             path.with_suffix(".build.log"))
        path.with_suffix(".build.json").write_text(json.dumps(usage))
        tmp.replace(path)
    return path


def describe(rec: Path) -> dict:
    """Events, anchors and held-out frames of a recording (its events left in the file)."""
    from edmcgs.pipeline import open_recording

    r = open_recording(rec, lazy_events=True)
    span = (r.events.t_end - r.events.t_start) / 1e6 if len(r.events) else 0.0
    return {"events": len(r.events), "anchors": len(r.anchors), "held_out": 0 if r.held_out is None
            else len(r.held_out), "seconds": span, "events_per_s": len(r.events) / max(span, 1e-9),
            "file_mb": rec.stat().st_size / 1e6}


def moving_poses(rec: Path) -> tuple[Path, dict]:
    """A handheld recording with the poses ``edmcgs record --poses auto`` estimates (cached beside it), and
    their cost and trajectory error against the true poses."""
    from bench.street3d import estimate, pose_accuracy
    from edmcgs.sensor.files.recording import read_recording

    auto, cost = estimate(rec)

    def accuracy() -> dict:
        _, acc = pose_accuracy(read_recording(rec, lazy_events=True), read_recording(auto, lazy_events=True))
        return {k: acc[k] for k in ("registered", "frames", "ate_pct")}

    return auto, cost | _cached(auto.with_suffix(".accuracy.json"), accuracy)


# ------------------------------------------------------------------------------- 2. training

def run_key(rec: Path, extra: list[str], run: int = 1, preset: str = "real") -> str:
    """The recording and the resolved config (and how it is run); ``run`` 2, 3, ...: the same training
    again, cached apart (a length repeated in ``--lengths``)."""
    from edmcgs.pipeline import build_config, open_recording

    cfg = build_config(preset, [], open_recording(rec, lazy_events=True)).to_dict()
    again = "" if run == 1 else f"_run{run}"
    return f"{rec.stem}_{_digest(rec.name, rec.stat().st_size, cfg, extra)}{again}"


def train(rec: Path, cache: Path, extra: list[str] | None = None, run: int = 1, preset: str = "real") -> dict:
    """``edmcgs train REC --config PRESET --threads 1`` (and ``extra``) in its own process, cached by
    ``run_key``."""
    extra = extra or []
    key = run_key(rec, extra, run, preset)
    ckpt = cache / f"{key}.ckpt"

    def make() -> dict:
        resumed_at, earlier_s = _interrupted(ckpt)
        print(f"training {rec.name} {' '.join(extra)}"
              + (f" from step {resumed_at}" if resumed_at else "") + " ...", file=sys.stderr)
        usage = measured_run([*_edmcgs(), "train", str(rec), "--config", preset, "--threads", "1", "-q",
                              "--resume" if resumed_at else "--force", "--history", str(cache / f"{key}.csv"),
                              "-o", str(ckpt), *extra], cache / f"{key}.log")
        # the interrupted part's process was never measured: its steps' own seconds stand in (one thread)
        usage["wall_s"] += earlier_s
        usage["cpu_s"] += earlier_s
        from edmcgs.model.checkpoint import load_checkpoint

        model = load_checkpoint(ckpt)
        return {"checkpoint": ckpt.name, "extra": extra, "trained_on": platform.node(),
                "trained_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                "checkpoint_mb": ckpt.stat().st_size / 1e6, "gaussians": len(model.gaussians),
                "control_points": model.control.num_points, "steps": _steps(cache / f"{key}.csv"),
                "load_average": os.getloadavg()[0], "resumed_at": resumed_at} | usage

    return _cached(cache / f"{key}.json", make)


def _interrupted(ckpt: Path) -> tuple[int | None, float]:
    """The step of the mid-training checkpoint an interrupted run left at ``ckpt`` (its train state
    inside) and the seconds its steps took; ``(None, 0.0)`` where there is none to continue."""
    if not ckpt.exists():
        return None, 0.0
    from edmcgs.errors import CheckpointError
    from edmcgs.model.checkpoint import read_checkpoint

    try:
        state = read_checkpoint(ckpt).get("train_state")
    except CheckpointError:
        return None, 0.0
    if not state or not state.get("step"):
        return None, 0.0
    return int(state["step"]), float(state.get("train_seconds", 0.0))


def _steps(history: Path) -> int | None:
    lines = history.read_text().splitlines()[1:] if history.exists() else []
    return int(lines[-1].split(",")[0]) if lines else None


def planned_steps(rec: Path, extra: list[str], preset: str = "real") -> int:
    """The run's steps as its config resolves them (``total_steps``), for a run that evaluated never."""
    from edmcgs.pipeline import build_config, open_recording

    r = open_recording(rec, lazy_events=True)
    overrides = [extra[i + 1] for i, a in enumerate(extra[:-1]) if a == "--set"]
    return build_config(preset, overrides, r).total_steps(len(r.anchors))


# ------------------------------------------------------------------------------- 3. scores

def score(rec: Path, run: dict, cache: Path) -> dict:
    """PSNR / SSIM of the checkpoint and of the three baselines on every held-out frame, cached."""
    def make() -> dict:
        from edmcgs.model.checkpoint import load_checkpoint
        from edmcgs.model.eval.baselines import score_baselines
        from edmcgs.model.eval.compare import Comparison
        from edmcgs.model.eval.evaluation import evaluate
        from edmcgs.pipeline import open_recording, training_data

        print(f"scoring {run['checkpoint']} ...", file=sys.stderr)
        data = training_data(open_recording(rec, lazy_events=True))
        model = load_checkpoint(cache / run["checkpoint"])
        return Comparison({"model": evaluate(model, data), **score_baselines(data)}).summary()

    return _cached(cache / f"{Path(run['checkpoint']).stem}.scores.json", make)


# ------------------------------------------------------------------------------- 4. serving

def serve_once(rec: Path, ckpt: Path, seconds: float) -> dict:
    """One server of ``ckpt`` replaying ``rec``: /render p50 (one client) and the server's RSS."""
    from bench.serve import measure_single
    from edmcgs.clients.client import Client
    from harness.server import ServerProcess

    server = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop", "--speed", "4"])
    try:
        server.wait_ready()
        with Client(server.url, timeout=60) as client:
            scene = client.scene()
            # the replay at 4x: renders from up to 2 s of the span (the whole of a shorter one)
            enough = min(scene["t_end_us"] - 20_000, scene["t_start_us"] + 2_000_000)
            while (client.scene()["renderable"] or {}).get("t_us_max", 0) < enough:
                time.sleep(0.1)
            intr = scene["intrinsics"]  # the camera's own size
            out = measure_single(client, client.scene(), seconds, (intr["width"], intr["height"]))
            out["server_rss_mb"] = server.rss_mb()
            out["num_gaussians"] = client.scene()["num_gaussians"]
    finally:
        server.stop()
    return out


def serve(recs: dict[int, Path], runs: dict[int, dict], cache: Path, rounds: int, seconds: float) -> dict:
    """{length: /render p50 (median over rounds), server RSS, ...}, the lengths alternated, cached."""
    key = _digest(sorted((s, runs[s]["checkpoint"]) for s in runs), rounds, seconds)

    def make() -> dict:
        lengths = sorted(runs)
        samples: dict[int, list[dict]] = {s: [] for s in lengths}
        for r in range(rounds):
            for s in (lengths if r % 2 == 0 else lengths[::-1]):
                print(f"serving {runs[s]['checkpoint']} (round {r + 1} of {rounds}) ...", file=sys.stderr)
                samples[s].append(serve_once(recs[s], cache / runs[s]["checkpoint"], seconds))
        return {str(s): {"render_p50_ms": float(np.median([x["render_p50_ms"] for x in xs])),
                         "render_server_p50_ms": float(np.median([x["render_server_p50_ms"] for x in xs])),
                         "server_rss_mb": float(max(x["server_rss_mb"] for x in xs)),
                         "num_gaussians": xs[0]["num_gaussians"],
                         "rounds": [x["render_p50_ms"] for x in xs]} for s, xs in samples.items()}

    return _cached(cache / f"serve_{key}.json", make)


# ------------------------------------------------------------------------------- 5. the event path

def tiled(source: Path, cache: Path, seconds: int) -> Path:
    """``source``'s events repeated back to back up to ``seconds`` (no frames), built once, a block at a
    time (never held whole)."""
    from edmcgs.sensor.events import Events
    from edmcgs.sensor.files.recording import RecordingFile, RecordingWriter

    path = cache / f"{source.stem}_tiled{seconds}s.h5"
    if path.exists():
        return path
    print(f"tiling {source.name} to {seconds} s ...", file=sys.stderr)
    with RecordingFile(source) as f:
        events = f.events()
        t0, t1 = events.t_start, events.t_end
        period = t1 - t0 + 1
        with RecordingWriter(path, width=f.width, height=f.height, sensor=f.sensor) as w:
            k = 0
            while k * period < seconds * 1_000_000:
                for i in range(0, len(events), 1 << 22):
                    block = events[i:i + (1 << 22)]
                    w.append_events(Events(block.t + k * period, block.x, block.y, block.p))
                k += 1
            w.finish(metadata={"tiled_from": source.name, "copies": k})
    return path


def event_path_child(path: Path) -> dict:
    """Replay ``path`` as fast as it reads into a server-sized ring, I_E of the newest 50 ms window taken
    as it fills (runs in its own process: its peak RSS is the event path's)."""
    from edmcgs.sensor.buffer.ingest import Ingest
    from edmcgs.sensor.buffer.ring import EventRingBuffer
    from edmcgs.sensor.event_map import accumulate
    from edmcgs.sensor.sources.open import open_source
    from edmcgs.sensor.sources.pacing import Pacing
    from edmcgs.server.settings import Settings

    imports_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6  # the interpreter and its modules
    ring = EventRingBuffer(Settings.model_fields["ring_events"].default)
    started = time.perf_counter()
    maps, nonzero = 0, 0
    with open_source(path, pacing=Pacing(factor=0)) as src:
        width, height = src.info.width, src.info.height
        ingest = Ingest(src, ring, reconnect=False).start()
        while ingest.running or maps == 0:
            wm = ring.watermark_us
            if wm is not None and ring.oldest_us is not None and wm - EVENT_WINDOW_US > ring.oldest_us:
                try:
                    emap = accumulate(ring.slice(wm - EVENT_WINDOW_US, wm), width, height)
                except Exception:  # the window overtaken by the writer: the next one
                    continue
                maps += 1
                nonzero += int(np.count_nonzero(emap))
            time.sleep(0.01)
        ingest.stop()
    if ingest.error is not None:
        raise ingest.error
    stats = ring.stats()
    return {"events": stats.pushed, "seconds": time.perf_counter() - started, "maps": maps,
            "ring_mb": stats.nbytes / 1e6, "overflowed": stats.overflowed, "nonzero_pixels": nonzero,
            "imports_gb": imports_gb}


def event_path(source: Path, cache: Path) -> dict:
    path = tiled(source, cache, EVENT_PATH_S)

    def make() -> dict:
        print(f"replaying {path.name} through the ring ...", file=sys.stderr)
        out = cache / "event_path.child.json"
        usage = measured_run([sys.executable, "-m", "bench.scale", "--event-path-child", str(path),
                              "--json", str(out)], cache / "event_path.log")
        return json.loads(out.read_text()) | usage | {"recording": path.name,
                                                        "file_gb": path.stat().st_size / 1e9}

    return _cached(cache / f"event_path_{_digest(path.name, path.stat().st_size)}.json", make)


# ------------------------------------------------------------------------------- 6. data-parallel

SPLIT = re.compile(r"data-parallel: (\d+) workers, (\d+) steps each, ([\d.]+) s training, ([\d.]+) s of it "
                   r"exchanging gradients \(([\d.]+) MB per step\)")
"""Rank 0's last line (``edmcgs.data_parallel``): how its training time splits."""


def data_parallel(rec: Path, cache: Path, extra: list[str] | None = None) -> dict:
    """1 and 2 local Ray Train workers on ``rec``: wall time, held-out PSNR, and rank 0's training time
    split into computing and exchanging gradients."""
    out = {}
    for workers in (1, 2):
        run = train(rec, cache, [*(extra or []), "--ray", "--workers", str(workers), "--ray-cpus", "2"])
        log = cache / f"{Path(run['checkpoint']).stem}.log"
        found = SPLIT.findall(log.read_text()) if log.exists() else []
        if found:
            _, steps, train_s, sync_s, mb = found[-1]
            run |= {"steps_per_worker": int(steps), "train_s": float(train_s), "exchange_s": float(sync_s),
                    "compute_s": float(train_s) - float(sync_s), "exchange_mb_per_step": float(mb)}
        out[workers] = run | {"scores": score(rec, run, cache)}
    return out


def cluster_estimate(two: dict, machines: int) -> float:
    """Speed-up of ``machines`` workers over one, from the split two workers measured (both halves under
    the same load): a step's computing and its exchange (on a network at least that: it grows with the
    bytes and the round trips), each of N workers taking 1/N of the steps."""
    compute = two["compute_s"] / two["steps_per_worker"]
    exchange = two["exchange_s"] / two["steps_per_worker"]
    return machines * compute / (compute + exchange)


# ------------------------------------------------------------------------------- the report

def _length(row: str) -> int:
    """A row's length in seconds: a row is named by it, ``"3"``, a repeated run with its number, ``"3#2"``."""
    return int(row.split("#")[0])


def summarise(results: dict) -> dict:
    s = {}
    for scene, rows in results["scenes"].items():
        margins = [r["margin_db"] for r in rows.values() if "margin_db" in r]
        if margins:
            s[f"{scene}_margin_db_min"] = min(margins)
        # the longest trained length against the shortest (the targets name 60 s against 3 s), each the
        # mean of its runs (a length repeated in --lengths: the runs alternate the lengths in one session)
        lengths = sorted({_length(k) for k, r in rows.items() if "cpu_per_s" in r})
        short, long = (lengths[0], lengths[-1]) if len(lengths) > 1 else (None, None)
        for key, name in (("cpu_per_s", "cpu_per_s_ratio"), ("render_p50_ms", "render_p50_ratio")):
            ours = {n: [r[key] for k, r in rows.items() if _length(k) == n and key in r]
                    for n in (short, long)}
            if short and ours[short] and ours[long]:
                s[f"{scene}_{name}_{long}_{short}"] = float(np.mean(ours[long]) / np.mean(ours[short]))
        if long and "peak_gb" in rows[str(long)]:
            s[f"{scene}_train_peak_gb_{long}"] = rows[str(long)]["peak_gb"]
    if "event_path" in results:
        s["event_path_peak_gb_600s"] = results["event_path"]["peak_gb"]
    if "ray" in results:
        one, two = results["ray"]["1"], results["ray"]["2"]
        s["ray_psnr_diff_db"] = abs(one["scores"]["model"]["psnr"] - two["scores"]["model"]["psnr"])
        s["ray_speedup_2_workers"] = one["wall_s"] / two["wall_s"]
        if "compute_s" in one and "compute_s" in two:
            s["ray_training_speedup_2_workers"] = one["train_s"] / two["train_s"]
            s["ray_exchange_share_2_workers"] = two["exchange_s"] / two["train_s"]
            for n in (4, 8, 16):
                s[f"ray_estimated_speedup_{n}_machines"] = cluster_estimate(two, n)
    return s


def markdown(r: dict, command: str) -> str:
    from edmcgs.model import config

    w, h = SIZES[r.get("size", "full")]
    overrides = r.get("overrides", [])
    sets = "".join(f" --set {kv}" for kv in overrides)
    per = next((kv.split("=", 1)[1] for kv in overrides if kv.startswith("steps_per_window=")), None)
    lines = ["# Scale benchmark: training, memory, quality and serving against the recording's length", "",
             f"`{command}` on {r['machine']}, a machine shared with other work. Scenes: `edmcgs synth "
             f"SCENE --fps 5 --seconds S --seed 0 --size {r.get('size', 'full')}` ({w}x{h}, DAVIS346-like); "
             f"training `edmcgs train REC --config PRESET --threads 1{sets}` in its own process (CPU time is "
             "user + system of that process, peak memory its resident set); PSNR over every held-out frame "
             "beside the three baselines on the same frames (margin: the model over the best of them).", ""]
    for scene, rows in r["scenes"].items():
        preset = PRESETS[scene]
        how = (f"`--config {preset}`, {per or config.preset(preset).steps_per_window} steps per span between "
               "anchors"
               + (", on the poses `edmcgs record REC --poses auto` estimated (structure from motion with "
                  "the IMU; below the table)" if preset == "moving" else ""))
        lines += [f"## {scene}", "", how + ".", "",
                  "| length | anchors | events | steps | train wall | train CPU | CPU per s of recording "
                  "| peak RSS | checkpoint | Gaussians | PSNR model | hold | blend | integrate | margin "
                  "| /render p50 | server RSS |", "|" + "---|" * 17]
        for name, row in sorted(rows.items(), key=lambda kv: (_length(kv[0]), kv[0])):
            length, _, run = name.partition("#")
            cells = [f"{length} s" + (f", run {run}" if run else ""), str(row["anchors"]),
                     f"{row['events'] / 1e6:.1f} M",
                     str(row.get("steps", "—"))
                     + (f" (resumed at {row['resumed_at']}: the time before it is its steps' own)"
                        if row.get("resumed_at") else "")]
            for key, fmt, unit in (("wall_min", ".1f", " min"), ("cpu_min", ".1f", " min"),
                                   ("cpu_per_s", ".1f", " s"), ("peak_gb", ".2f", " GB"),
                                   ("checkpoint_mb", ".1f", " MB"), ("gaussians", ",", ""),
                                   ("psnr", ".2f", ""),
                                   ("hold_last", ".2f", ""), ("blend", ".2f", ""), ("integrate", ".2f", ""),
                                   ("margin_db", "+.2f", ""), ("render_p50_ms", ".1f", " ms"),
                                   ("server_rss_mb", ".0f", " MB")):
                cells.append("—" if row.get(key) is None else f"{row[key]:{fmt}}{unit}")
            lines.append("| " + " | ".join(cells) + " |")
        posed = [(name, row["poses"]) for name, row in rows.items() if "poses" in row]
        if posed:
            lines += ["", "| length | frames registered | ATE / path (evo, Sim(3)) | wall | CPU |",
                      "|---|---|---|---|---|"]
            lines += [f"| {name} s | {p['registered']} of {p['frames']} | {p['ate_pct']:.2f} % | "
                      f"{p['wall_s']:.0f} s | {p['cpu_s']:.0f} s |" for name, p in posed]
        missing = sorted({_length(name) for name, row in rows.items() if "wall_min" not in row})
        if missing:
            listed = ",".join(map(str, missing))
            lines += ["", f"Not trained yet: {listed} s; `python -m bench.scale --only train "
                          f"--scenes {scene} --lengths {listed}` trains them (each length cached "
                          "as it finishes)."]
        lines.append("")
    if "event_path" in r:
        e = r["event_path"]
        lines += ["## The event path alone, 10 minutes", "",
                  f"`{e['recording']}` ({e['file_gb']:.2f} GB: the 10 s traffic recording tiled to "
                  f"{EVENT_PATH_S} s, {e['events'] / 1e6:.0f} M events) replayed as fast as it reads through "
                  f"the HDF5 replay into the server's ring ({e['ring_mb']:.0f} MB), I_E of the newest "
                  f"{EVENT_WINDOW_US // 1000} ms taken {e['maps']} times as it filled: {e['seconds']:.0f} s, "
                  f"peak resident memory **{e['peak_gb']:.2f} GB**"
                  + (f", {e['imports_gb']:.2f} GB of it the interpreter and its modules (torch, numba) "
                     "before the first event" if "imports_gb" in e else "") + ".", ""]
    if "ray" in r:
        lines += ["## Data-parallel training on Ray Train", "",
                  f"`edmcgs train REC --config real --threads 1{sets} --ray --workers N --ray-cpus 2` on the "
                  "shortest traffic recording, the workers local (gloo over loopback, the machine's 2 "
                  "cores); a step of N workers takes N samples, so each takes 1/N of the steps. Rank 0's "
                  "training time (evaluations and start-up left out) splits into computing and exchanging "
                  "gradients (the all-reduce and the union of the drawn rows, waits for the slower worker "
                  "included).", "",
                  "| workers | wall | PSNR model | steps per worker | training | computing | exchanging "
                  "| MB per step |", "|---|---|---|---|---|---|---|---|"]
        for n, run in sorted(r["ray"].items()):
            cells = [n, f"{run['wall_s'] / 60:.1f} min", f"{run['scores']['model']['psnr']:.2f}",
                     str(run.get("steps_per_worker", "—"))]
            for key in ("train_s", "compute_s", "exchange_s"):
                cells.append("—" if key not in run else f"{run[key]:.0f} s")
            cells.append("—" if "exchange_mb_per_step" not in run else f"{run['exchange_mb_per_step']:.2f}")
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["```", table(r["summary"], TARGETS), "```", ""]
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench.scale", description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, of {list(SCENES)}")
    p.add_argument("--lengths", default=",".join(map(str, LENGTHS)),
                   help="seconds, comma-separated (a length repeated trains again: 3,60,3 alternates them)")
    p.add_argument("--only", default=",".join(STEPS), help=f"steps to run, of {list(STEPS)} (the others "
                                                           "are read from the cache where they are)")
    p.add_argument("--out", type=Path, default=Path("reports"), help="where scale.md and bench/scale.json go")
    p.add_argument("--cache", type=Path, default=Path("reports/cache/scale"), help="recordings, runs, scores")
    p.add_argument("--size", choices=sorted(SIZES), default="full", help="the recordings' resolution "
                   "(edmcgs synth --size; small: 173x130)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override of every training (edmcgs train --set), e.g. steps_per_window=20")
    p.add_argument("--serve-rounds", type=int, default=2)
    p.add_argument("--serve-seconds", type=float, default=8.0)
    p.add_argument("--event-path-child", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.event_path_child is not None:  # the measured process of step 5
        write_json(args.json, event_path_child(args.event_path_child))
        return 0
    import torch

    from edmcgs.model.eval.baselines import BASELINES, SHORT
    torch.set_num_threads(1)
    scenes = [s for s in args.scenes.split(",") if s]
    lengths = [int(s) for s in args.lengths.split(",") if s]
    only = set(args.only.split(","))
    unknown = [s for s in scenes if s not in SCENES] + sorted(only - set(STEPS))
    if unknown:
        raise SystemExit(f"bench.scale: unknown {unknown}; scenes {list(SCENES)}, steps {list(STEPS)}")
    cache = args.cache
    cache.mkdir(parents=True, exist_ok=True)
    sets = [a for kv in args.overrides for a in ("--set", kv)]
    results = {"machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "size": args.size,
               "overrides": args.overrides, "scenes": {}}
    for scene in scenes:
        rows, recs, runs = {}, {}, {}
        for i, length in enumerate(lengths):
            again = lengths[:i].count(length) + 1  # a repeated length trains again: its run number
            name = str(length) if again == 1 else f"{length}#{again}"
            path = recording_path(cache, scene, length, args.size)
            if "build" in only:
                path = recording(cache, scene, length, args.size)
            if not path.exists():
                continue
            row = {}
            if PRESETS[scene] == "moving":  # trained on the poses it estimates, as a user's would be
                path, poses = moving_poses(path)
                row["poses"] = poses
            recs[length] = path
            row |= describe(path)
            key = run_key(path, sets, again, PRESETS[scene])
            if "train" in only or (cache / f"{key}.json").exists():
                run = train(path, cache, sets, again, PRESETS[scene])
                if again == 1:
                    runs[length] = run  # served: the first run of each length
                row |= {"wall_min": run["wall_s"] / 60, "cpu_min": run["cpu_s"] / 60,
                        "cpu_per_s": run["cpu_s"] / row["seconds"], "peak_gb": run["peak_gb"],
                        "checkpoint_mb": run["checkpoint_mb"], "gaussians": run["gaussians"],
                        "steps": run["steps"] or planned_steps(path, sets, PRESETS[scene]),
                        "load_average": run.get("load_average"), "resumed_at": run.get("resumed_at")}
                scores_path = cache / f"{Path(run['checkpoint']).stem}.scores.json"
                if "score" in only or scores_path.exists():
                    sc = score(path, run, cache)
                    row |= {SHORT[name]: sc[name]["psnr"] for name in BASELINES}
                    row["psnr"] = sc["model"]["psnr"]
                    row["margin_db"] = row["psnr"] - max(sc[name]["psnr"] for name in BASELINES)
            rows[name] = row
        if runs and "serve" in only:
            served = serve(recs, runs, cache, args.serve_rounds, args.serve_seconds)
            for length, s in served.items():
                rows[length] |= {k: v for k, v in s.items() if k != "rounds"}
        results["scenes"][scene] = rows
    if "events" in only:
        results["event_path"] = event_path(recording(cache, "traffic", EVENT_SOURCE_S), cache)
    shortest = recording_path(cache, "traffic", min(lengths), args.size)
    if "ray" in only and shortest.exists():
        results["ray"] = {str(k): v for k, v in data_parallel(shortest, cache, sets).items()}
    results["summary"] = summarise(results)
    results["targets_met"] = {k: meets(v, TARGETS[k]) for k, v in results["summary"].items() if k in TARGETS}
    command = "python -m bench.scale" + (f" {' '.join(argv)}" if argv else "")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "scale.md").write_text(markdown(results, command))
    write_json(args.out / "bench" / "scale.json", results)
    write_json(args.json, results)
    print(table(results["summary"], TARGETS))
    print(f"wrote {args.out / 'scale.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
