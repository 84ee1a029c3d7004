"""The GPU figures in one run: the CUDA tests, then the benchmarks with ``--device``, into one JSON.

    python -m bench.gpu --out DIR [--device cuda] [--deadline 540] [--real REC.h5] [--tiny]

``scripts/gpu_check.sh`` runs it on a fresh GPU machine (after installing what that lacks). Parts, in
this order, each a subprocess with its own time limit, cut to what is left of ``--deadline`` seconds:

    render      bench.render at 346x260 with 8k Gaussians: each CUDA path, forward and forward + backward
    train_real  the ``real`` preset trained from scratch on ``--real`` (a 346x260 street, default
                ``edmcgs synth traffic --fps 5 --seconds 3 --seed 0``) for 1500 steps, or as many as its
                budget allows: steps/s (over the run, and over its budget's second half), training
                seconds, wall seconds, held-out PSNR / SSIM of all frames
    tests       the CUDA tests (tests/raster and test_train_device.py, -k "cuda or gsplat")
    serve       bench.serve on the demo: GET /render p50 (one client) and four clients' renders/s
    train_step  bench.train_step with the ``real`` preset on ``--real``: per stage, ops, launches, syncs
    train_demo  the ``demo`` preset on the bundled demo recording, as train_real
    train_real_compile, train_demo_compile  the same with ``--compile`` (their compile included)
    eval        edmcgs eval --demo on the device (the bundled checkpoint against its held-out frames)

A part cut by its limit is recorded with what it got (a training run stops at its budget and reports the
steps it made). DIR gets ``gpu.json`` (every part: command, return code, seconds, results; its ``summary``
holds the figures the docs quote) and ``gpu.log`` (their output). ``--tiny``: CPU-sized settings (a few
steps, short measurements, the bundled demo in place of ``--real``) to check this driver without a GPU.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.results import write_json

ROOT = Path(__file__).resolve().parents[1]
STEPS = 1500
CUDA_TESTS = ["tests/raster", "tests/model/test_train_device.py"]
"""Where the CUDA cases are; ``-k "cuda or gsplat"`` picks them (and test_rasterize_gsplat.py's CPU ones)."""
BUDGETS = {"render": 60, "train_real": 90, "tests": 150, "serve": 60, "train_step": 75, "train_demo": 40,
           "train_real_compile": 60, "train_demo_compile": 45, "eval": 45}
"""Seconds each part may take on the GPU; a training run's are its training alone (its setup and the final
scoring get another ``TRAIN_EXTRA``)."""
TRAIN_EXTRA = 45
TRAIN_PARTS = ("train_real", "train_real_compile", "train_demo", "train_demo_compile")
"""The parts that train (``train_run``), each ``train_PRESET[_compile]``."""
TAIL_LINES = 12
"""Last output lines of each part kept in gpu.json (all of it is in gpu.log)."""
PARTS = tuple(BUDGETS)


def _device_info(device: str) -> dict:
    import torch

    info = {"torch": torch.__version__, "python": platform.python_version(), "device": device}
    if device.startswith("cuda"):
        info |= {"gpu": torch.cuda.get_device_name(), "cuda": torch.version.cuda}
    from edmcgs.model.render import rasterize_gsplat

    info["gsplat_installed"] = rasterize_gsplat.available()
    if device.startswith("cuda") and rasterize_gsplat.available():
        info["gsplat_error"] = rasterize_gsplat.extension_error()
    return info


def train_run(recording: Path, preset: str, device: str, steps: int, budget: float, overrides: list[str],
              json_path: Path | None = None, compile: bool = False) -> dict:
    """Train ``preset`` from scratch on ``recording`` for ``steps`` steps or until ``budget`` seconds of
    training have passed (the step in flight finishes); then score every held-out frame. The figures are
    written to ``json_path`` before the scoring too, so that a run cut during it keeps them."""
    from edmcgs.model.train.trainer import Trainer
    from edmcgs.pipeline import build_config, new_model, open_recording, training_data

    start = time.perf_counter()
    rec = open_recording(recording, progress=False)
    data = training_data(rec)
    cfg = build_config(preset, [*overrides, f"iterations={steps}"], rec)
    model = new_model(data, cfg)
    trainer = Trainer(model, data, device=device, progress=False, compile=compile)
    setup = time.perf_counter() - start
    stop = threading.Event()
    marks = []  # (wall, step) at half the budget and at the end: the rate past compile and warm-up
    timers = [threading.Timer(budget / 2, lambda: marks.append((time.perf_counter(), trainer.step))),
              threading.Timer(budget, stop.set)]
    for timer in timers:
        timer.start()
    started = time.perf_counter()
    try:
        history = trainer.fit(None, until=steps, stop=stop)
    finally:
        for timer in timers:
            timer.cancel()
    fit_wall = time.perf_counter() - started
    done = trainer.step
    late = None
    if marks and done > marks[0][1]:
        late = (done - marks[0][1]) / (started + fit_wall - marks[0][0])
    out = {"preset": preset, "compile": compile, "recording": str(recording),
           "size": f"{rec.width}x{rec.height}",
           "steps_asked": steps, "steps_done": done, "completed": done >= steps,
           "train_seconds": trainer.train_seconds, "fit_wall_seconds": fit_wall, "setup_seconds": setup,
           "steps_per_second": done / trainer.train_seconds if trainer.train_seconds else None,
           "late_steps_per_second": late,
           "gaussians": len(trainer.model.gaussians), "history": history}
    out["projected_seconds_for_asked_steps"] = steps / out["steps_per_second"] if done else None
    write_json(json_path, out)
    if data.evaluable().size:
        final = trainer.evaluate()
        out |= {"heldout_psnr": final["psnr"], "heldout_ssim": final["ssim"],
                "heldout_frames": final["frames"]}
        write_json(json_path, out)
    return out


def _parts(args) -> list[tuple[str, list[str], float]]:
    """(name, command, budget seconds) of each part, in order."""
    py, dev = [sys.executable], ["--device", args.device]
    tiny = args.tiny
    budgets = {k: v / 3 if tiny else v for k, v in BUDGETS.items()}
    real = ["--real", str(args.real)]
    out = args.out
    steps = "20" if tiny else str(STEPS)
    small = ["--set", "init_points=2000"] if tiny else []
    parts = {
        "tests": [*py, "-m", "pytest", *CUDA_TESTS, "-k", "cuda or gsplat", "-q", "-p", "no:cacheprovider",
                  "-x" if tiny else "-ra"],
        "render": [*py, "-m", "bench.render", *dev, "--sizes", "346x260", "--counts", "8000",
                   "--runs", "10" if tiny else "50", "--json", str(out / "render.json")]
        + (["--paths", "torch", "--threads", "1"] if tiny else []),
        "serve": [*py, "-m", "bench.serve", *dev, "--seconds", "1" if tiny else "4",
                  "--json", str(out / "serve.json")],
        "eval": [*py, "-m", "edmcgs.cli", "eval", "--demo", "-q", *dev],
        "train_step": [*py, "-m", "bench.train_step", *dev, "--recording", str(args.real), "--config", "real",
                       "--steps", "3" if tiny else "20", *small,
                       "--json", str(out / "train_step.json")],
    }
    for name in TRAIN_PARTS:
        preset = name.split("_")[1]
        parts[name] = [*py, "-m", "bench.gpu", "--train", preset, *(real if preset == "real" else []), *dev,
                       *(["--compile"] if name.endswith("_compile") else []), "--steps", steps,
                       "--budget", str(budgets[name]), *small, "--json", str(out / f"{name}.json")]
    return [(name, parts[name], budgets[name] + (TRAIN_EXTRA if name in TRAIN_PARTS else 0))
            for name in PARTS if name in args.parts]


def _run_part(name: str, cmd: list[str], limit: float, log) -> dict:
    """Run one part, its output appended to ``log``; its last lines are kept in the result too."""
    log.write(f"\n===== {name}: {' '.join(cmd)} (limit {limit:.0f} s)\n")
    log.flush()
    started = time.perf_counter()
    with tempfile.TemporaryFile("w+") as output:
        try:
            done = subprocess.run(cmd, cwd=ROOT, stdout=output, stderr=subprocess.STDOUT, timeout=limit,
                                  check=False)
            code = done.returncode
        except subprocess.TimeoutExpired:
            code = "timeout"
        output.seek(0)
        text = output.read()
    log.write(text)
    seconds = time.perf_counter() - started
    log.write(f"===== {name}: exit {code} after {seconds:.1f} s\n")
    log.flush()
    tail = [line[-300:] for line in text.replace("\r", "\n").splitlines() if line.strip()][-TAIL_LINES:]
    return {"command": cmd, "returncode": code, "seconds": round(seconds, 1), "output_tail": tail}


def summarize(parts: dict) -> dict:
    """The figures the docs quote, from the parts' results (those that ran)."""
    out: dict = {}
    for row in parts.get("render", {}).get("results", {}).get("rows", []):
        out[f"{row['path']}_{row['pass']}_ms"] = row["median_ms"]
    for name, part in parts.items():
        res = part.get("results", {})
        if name not in TRAIN_PARTS or not res.get("steps_done"):
            continue
        key = name.removeprefix("train_")
        out |= {f"{key}_steps": res["steps_done"], f"{key}_train_s": res["train_seconds"],
                f"{key}_steps_per_s": res["steps_per_second"],
                f"{key}_seconds_for_{res['steps_asked']}": res["train_seconds"] if res["completed"]
                else res["projected_seconds_for_asked_steps"]}
        if res.get("late_steps_per_second"):  # the second half of the budget: past compile and warm-up
            out[f"{key}_late_steps_per_s"] = res["late_steps_per_second"]
        if "heldout_psnr" in res:
            out[f"{key}_psnr"], out[f"{key}_ssim"] = res["heldout_psnr"], res["heldout_ssim"]
    serve = parts.get("serve", {}).get("results", {})
    for k in ("render_p50_ms", "render_rps_4_clients", "render_p50_ms_4_clients"):
        if k in serve:
            out[f"serve_{k}"] = serve[k]
    step = parts.get("train_step", {}).get("results", {})
    if step:
        out["train_step_ms"] = step["step_ms_median"]
        out["train_step_gpu_ms"] = step.get("step_gpu_ms")
        out["train_step_syncs"] = (step.get("cuda_syncs") or {}).get("per_step")
    return out


def drive(args) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    deadline = time.perf_counter() + args.deadline
    report = {"started_unix": time.time(), "info": _device_info(args.device), "parts": {}}
    with open(args.out / "gpu.log", "a") as log:
        for name, cmd, budget in _parts(args):
            left = deadline - time.perf_counter()
            if left < 20:
                report["parts"][name] = {"command": cmd, "returncode": "skipped: no time left"}
                continue
            part = _run_part(name, cmd, min(budget, left), log)
            produced = args.out / f"{name}.json"
            if produced.exists():
                part["results"] = json.loads(produced.read_text())
                produced.unlink()  # folded into gpu.json: few files come back from a device
            report["parts"][name] = part
            report["summary"] = summarize(report["parts"])
            write_json(args.out / "gpu.json", report)
    failed = [n for n, p in report["parts"].items() if p.get("returncode") != 0]
    print(f"bench.gpu: {len(report['parts']) - len(failed)} of {len(report['parts'])} parts ran cleanly"
          + (f"; not: {', '.join(failed)}" if failed else "") + f"; {args.out / 'gpu.json'}")
    return 0 if not failed else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.gpu", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, help="folder for gpu.json and gpu.log")
    p.add_argument("--device", default="cuda", help="torch device (default cuda; cpu with --tiny)")
    p.add_argument("--deadline", type=float, default=540.0, help="seconds for all parts (default 540)")
    p.add_argument("--real", type=Path, help="the 346x260 recording of the real preset's parts")
    p.add_argument("--tiny", action="store_true", help="CPU-sized settings, to check the driver")
    p.add_argument("--parts", type=lambda t: [v for v in t.split(",") if v], default=list(PARTS),
                   help=f"comma-separated subset of {','.join(PARTS)} (default: all, in that order)")
    p.add_argument("--train", metavar="PRESET", help=argparse.SUPPRESS)  # one training part, in-process
    p.add_argument("--steps", type=int, default=STEPS, help=argparse.SUPPRESS)
    p.add_argument("--budget", type=float, default=120.0, help=argparse.SUPPRESS)
    p.add_argument("--set", dest="overrides", action="append", default=[], help=argparse.SUPPRESS)
    p.add_argument("--compile", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    from edmcgs.errors import InvalidInputError
    from edmcgs.model.devices import check_device

    try:
        check_device(args.device)
    except InvalidInputError as exc:
        p.error(str(exc))
    if args.train:
        from edmcgs.server import demo

        rec = args.real if args.real is not None else demo.files()[1]
        result = train_run(rec, args.train, args.device, args.steps, args.budget, args.overrides, args.json,
                           args.compile)
        print(json.dumps({k: v for k, v in result.items() if k != "history"}, indent=1))
        return 0
    if args.out is None:
        p.error("--out is required")
    if not args.parts or any(part not in PARTS for part in args.parts):
        p.error(f"--parts must name some of {', '.join(PARTS)}")
    if args.real is None:
        if not args.tiny:
            p.error("--real REC.h5 is required (the 346x260 street: scripts/gpu_wheels.sh builds one)")
        from edmcgs.server import demo

        args.real = demo.files()[1]
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    return drive(args)


if __name__ == "__main__":
    sys.exit(main())
