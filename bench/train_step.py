"""Where a training step's time goes: the stages of ``Trainer.train_step``, profiled.

    .venv/bin/python -m bench.train_step [--checkpoint CKPT --recording REC | --recording REC --config P]
        [--set KEY=VALUE] [--at 0.9] [--steps 30] [--threads 1] [--json PATH]

Trains on from a checkpoint (default: the bundled demo, trained, with its recording), or from a new
model built from ``--recording`` with the preset; moves the step counter to ``--at`` of the schedule
(so that the deformation, the event pairs and densification run as they do then), warms up, then
runs ``--steps`` steps under the torch profiler. Prints, per stage (the named ranges of
``train_step``), its wall time per step, inclusive of what it calls, and its share of the step; then
the slowest ops by self time, which splits the backward into its autograd nodes
(``CompositeFastBackward``, ...). The rasterizer is ``EDMCGS_RASTERIZER``'s
(numba on the CPU by default). Timings are wall clock on a shared machine: the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from bench.results import write_json

WARMUP = 5


def profile_steps(trainer, steps: int) -> tuple[dict, list[dict], float]:
    """({stage: ms per step}, the 12 slowest ops by self time, median ms per step) of ``steps`` steps."""
    from torch.profiler import ProfilerActivity, profile, record_function

    walls = []
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            start = time.perf_counter()
            with record_function("step"):
                trainer.train_step()
            walls.append((time.perf_counter() - start) * 1e3)
    events = prof.key_averages()
    # the trainer's ranges: "part: what" or one of these (torch's ops are "aten::...", "autograd::...")
    named = ("step", "backward", "optimizer step", "density control", "next anchor")
    ranges = {e.key: e.cpu_time_total / steps / 1e3 for e in events
              if (": " in e.key and "::" not in e.key) or e.key in named}
    ops = sorted((e for e in events if e.key not in ranges), key=lambda e: -e.self_cpu_time_total)[:12]
    top = [{"op": e.key, "self_ms": e.self_cpu_time_total / steps / 1e3, "calls": e.count // steps}
           for e in ops]
    return ranges, top, float(np.median(walls))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.train_step", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path, help="train on from this checkpoint (default: the bundled "
                                                   "demo's, unless --recording alone is given)")
    p.add_argument("--recording", type=Path, help="its recording; alone: a new model with --config")
    p.add_argument("--config", default="demo", help="preset of a new model (default: demo)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--at", type=float, default=0.9, help="fraction of the schedule to profile at (0.9)")
    p.add_argument("--steps", type=int, default=30, help="profiled steps (30)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1, as edmcgs train's default)")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    if not 0 <= args.at <= 1:
        p.error(f"--at must lie in [0, 1], got {args.at}")
    if args.steps < 1 or args.threads < 1:
        p.error("--steps and --threads must be >= 1")
    import torch

    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.render.rasterize import backend_of
    from edmcgs.model.train.trainer import Trainer
    from edmcgs.pipeline import build_config, new_model, open_recording, training_data
    from edmcgs.server import demo

    torch.set_num_threads(args.threads)
    if args.checkpoint is None and args.recording is None:
        args.checkpoint, args.recording = demo.files()
    if args.checkpoint is not None and args.recording is None:
        p.error("--checkpoint needs --recording (the recording it was trained on)")
    path = args.recording
    rec = open_recording(path, progress=False)
    data = training_data(rec)
    if args.checkpoint is not None:
        model = load_checkpoint(args.checkpoint)
        model.config = cfg = model.config.with_overrides(args.overrides)
        source = f"{args.checkpoint} + {path}"
    else:
        cfg = build_config(args.config, args.overrides, rec)
        model = new_model(data, cfg)
        source = f"{path}, a new model ({args.config} preset)"
    trainer = Trainer(model, data, progress=False)
    trainer.step = round(args.at * cfg.iterations)
    for _ in range(WARMUP):
        trainer.train_step()
    ranges, top, step_ms = profile_steps(trainer, args.steps)
    total = ranges.pop("step")
    rasterizer = backend_of(None, trainer.model.gaussians.means)
    print(f"train_step on {source} ({rec.width}x{rec.height}, "
          f"{len(trainer.model.gaussians)} Gaussians), at {args.at:.0%} of {cfg.iterations} steps, "
          f"{args.steps} steps, {args.threads} thread(s), rasterizer {rasterizer}")
    print(f"{'stage':<30}{'ms/step':>10}{'share':>8}")
    for name, ms in sorted(ranges.items(), key=lambda kv: -kv[1]):
        print(f"{name:<30}{ms:>10.2f}{ms / total:>8.0%}")
    rest = total - sum(ranges.values())
    print(f"{'(outside the stages)':<30}{rest:>10.2f}{rest / total:>8.0%}")
    print(f"{'step (profiled)':<30}{total:>10.2f}\n{'step (median, wall)':<30}{step_ms:>10.2f}")
    print(f"\nslowest ops by self time (ms/step):\n{'op':<44}{'self ms':>9}{'calls':>7}")
    for row in top:
        print(f"{row['op'][:44]:<44}{row['self_ms']:>9.2f}{row['calls']:>7}")
    load = os.getloadavg()[0]
    print(f"load average {load:.1f} on {os.cpu_count()} CPUs (a shared machine: times are noisy)")
    write_json(args.json, {"source": source, "at": args.at, "steps": args.steps,
                           "threads": args.threads, "rasterizer": rasterizer,
                           "gaussians": len(trainer.model.gaussians),
                           "step_ms_median": step_ms, "step_ms_profiled": total, "stages_ms": ranges,
                           "top_ops": top, "load_average_1m": load})
    return 0


if __name__ == "__main__":
    sys.exit(main())
