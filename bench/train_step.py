"""Where a training step's time goes: the stages of ``Trainer.train_step``, profiled.

    .venv/bin/python -m bench.train_step [--checkpoint CKPT --recording REC | --recording REC --config P]
        [--set KEY=VALUE] [--at 0.9] [--steps 30] [--timed 0] [--threads 1] [--device cpu|cuda]
        [--json PATH]

Trains on from a checkpoint (default: the bundled demo, trained, with its recording), or from a new
model built from ``--recording`` with the preset; moves the step counter to ``--at`` of the schedule
(so that the deformation, the event pairs and densification run as they do then), warms up, then
runs ``--timed`` steps timed alone (the torch profiler's memory grows with the steps it holds: over a
few hundred steps of a long recording, many GB) and ``--steps`` steps under the torch profiler. Prints,
per stage (the named ranges of ``train_step``), its wall time per step, inclusive of what it calls,
and its share of the step; then the slowest ops by self time, which splits the backward into its
autograd nodes (``CompositeFastBackward``, ...). The rasterizer is ``EDMCGS_RASTERIZER``'s (numba on the
CPU by default, gsplat on CUDA where installed, else torch). Timings are wall clock on a
shared machine: the load average is printed.

Then what a step reads back to the host, by the line that asks (``harness/host_reads``: on a GPU
each such read waits for the device, so they are what keeps it from running ahead); on CUDA also the
synchronising CUDA calls torch itself reports (``torch.cuda.set_sync_debug_mode``), the stages' GPU time,
and step times that wait for the device at each step's end.
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
READ_STEPS = 5
"""Steps whose host reads (and CUDA synchronisations) are counted."""


def profile_steps(trainer, steps: int) -> tuple[dict, dict, list[dict], float, dict]:
    """({stage: host ms per step}, {stage: GPU ms per step} (empty on the CPU), the 12 slowest ops by self
    time (on CUDA: by GPU time), median wall ms per step, {"ops": torch ops per step not called by another,
    "launches": kernel launches per step (CUDA)}) of ``steps`` steps. On a GPU each op costs the host
    about 10 us to issue: a step of thousands waits on Python, not on its kernels."""
    from torch.profiler import ProfilerActivity, profile, record_function

    cuda = trainer.device.type == "cuda"
    sync = _sync(trainer.device)
    walls = []
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        for _ in range(steps):
            start = time.perf_counter()
            with record_function("step"):
                trainer.train_step()
            sync()
            walls.append((time.perf_counter() - start) * 1e3)
    counts = {"ops": 0, "launches": 0}
    for e in prof.events():
        if e.name.startswith("aten::"):
            parent = e.cpu_parent
            while parent is not None and not parent.name.startswith("aten::"):
                parent = parent.cpu_parent
            counts["ops"] += parent is None
        elif e.name in ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx"):
            counts["launches"] += 1
    counts = {k: v / steps for k, v in counts.items()}
    events = prof.key_averages()
    # the trainer's ranges: "part: what" or one of these (torch's ops are "aten::...", "autograd::...")
    named = ("step", "backward", "optimizer step", "density control", "next anchor")
    # on CUDA a range is listed twice, as its host span and as its annotation on the device's timeline
    # (no host time): each figure is the larger of the two
    ranges: dict[str, float] = {}
    gpu: dict[str, float] = {}
    for e in events:
        if (": " in e.key and "::" not in e.key) or e.key in named:
            ranges[e.key] = max(ranges.get(e.key, 0.0), e.cpu_time_total / steps / 1e3)
            if cuda:
                gpu[e.key] = max(gpu.get(e.key, 0.0), getattr(e, "device_time_total", 0.0) / steps / 1e3)
    def rank(e) -> float:
        return -getattr(e, "self_device_time_total", 0.0) if cuda else -e.self_cpu_time_total

    ops = sorted((e for e in events if e.key not in ranges), key=rank)[:12]
    top = [{"op": e.key, "self_ms": e.self_cpu_time_total / steps / 1e3, "calls": e.count // steps}
           | ({"gpu_ms": getattr(e, "self_device_time_total", 0.0) / steps / 1e3} if cuda else {})
           for e in ops]
    return ranges, gpu, top, float(np.median(walls)), counts


def op_cost_us(device, ops: int = 20_000) -> float:
    """Host microseconds to issue one small op on ``device`` (an in-place add, the device waited for at the
    end): the floor of each op of a step when a GPU waits on Python."""
    import torch

    x = torch.zeros(16, device=device)
    sync = _sync(x.device)
    sync()
    start = time.perf_counter()
    for _ in range(ops):
        x.add_(1)
    sync()
    return (time.perf_counter() - start) / ops * 1e6


def _sync(device):
    """What waits for ``device``'s queued work (nothing on the CPU)."""
    import torch

    return torch.cuda.synchronize if device.type == "cuda" else (lambda: None)


def timed_steps(trainer, steps: int) -> dict | None:
    """{median_ms, last_half_median_ms, mean_ms} of ``steps`` steps' wall time, unprofiled (None: none)."""
    if steps < 1:
        return None
    sync = _sync(trainer.device)
    walls = []
    for _ in range(steps):
        start = time.perf_counter()
        trainer.train_step()
        sync()
        walls.append((time.perf_counter() - start) * 1e3)
    return {"steps": steps, "median_ms": float(np.median(walls)),
            "last_half_median_ms": float(np.median(walls[steps // 2:])), "mean_ms": float(np.mean(walls))}


def host_reads(trainer, steps: int = READ_STEPS) -> dict:
    """What ``steps`` steps read back to the host: per step in all, and per step by line (project code
    that asked itself; reads inside libraries, such as torch's CPU optimizer, under their caller)."""
    from harness.host_reads import HostReads

    with HostReads() as reads:
        for _ in range(steps):
            trainer.train_step()
    by_site = {site: n / steps for site, n in reads.sites.most_common()}
    return {"per_step": reads.total / steps, "direct_per_step": sum(reads.direct.values()) / steps,
            "by_site": by_site}


def cuda_syncs(trainer, steps: int = READ_STEPS) -> dict:
    """The synchronising CUDA calls of ``steps`` steps as torch reports them, per step and by line."""
    import collections
    import warnings

    import torch

    sites: collections.Counter[str] = collections.Counter()
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(steps):
                trainer.train_step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    root = Path(__file__).resolve().parents[1]
    for w in caught:
        if "synchroniz" in str(w.message):
            path = Path(w.filename)
            name = str(path.relative_to(root)) if path.is_relative_to(root) else path.name
            sites[f"{name}:{w.lineno}"] += 1
    return {"per_step": sum(sites.values()) / steps,
            "by_site": {site: n / steps for site, n in sites.most_common()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.train_step", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path, help="train on from this checkpoint (default: the bundled "
                                                   "demo's, unless --recording alone is given)")
    p.add_argument("--recording", type=Path, help="its recording; alone: a new model with --config")
    p.add_argument("--config", default="demo", help="preset of a new model (default: demo)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--at", type=float, default=0.9, help="fraction of the schedule to profile at (0.9)")
    p.add_argument("--steps", type=int, default=30, help="profiled steps (30)")
    p.add_argument("--timed", type=int, default=0, help="steps timed before those, without the profiler "
                   "(0; a few hundred show a long recording's steady state, cheaply)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1, as edmcgs train's default)")
    p.add_argument("--device", default="cpu", help="torch device to train on (cpu, cuda, cuda:N)")
    p.add_argument("--compile", action="store_true", help="the skinning by torch.compile (edmcgs train "
                                                          "--compile); compiled during the warm-up")
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    if not 0 <= args.at <= 1:
        p.error(f"--at must lie in [0, 1], got {args.at}")
    if args.steps < 1 or args.threads < 1 or args.timed < 0:
        p.error("--steps and --threads must be >= 1, --timed >= 0")
    import torch

    from edmcgs.errors import InvalidInputError
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.devices import check_device
    from edmcgs.model.render.rasterize import backend_of
    from edmcgs.model.train.trainer import Trainer
    from edmcgs.pipeline import build_config, new_model, open_recording, training_data
    from edmcgs.server import demo

    try:
        check_device(args.device)
    except InvalidInputError as exc:
        p.error(str(exc))
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
    trainer = Trainer(model, data, device=args.device, progress=False, compile=args.compile)
    trainer.step = round(args.at * trainer.total_steps)
    for _ in range(WARMUP):
        trainer.train_step()
    timed = timed_steps(trainer, args.timed)
    ranges, gpu, top, step_ms, counts = profile_steps(trainer, args.steps)
    total = ranges.pop("step")
    gpu_total = gpu.pop("step", None)
    cuda = trainer.device.type == "cuda"
    rasterizer = backend_of(None, trainer.model.gaussians.means)
    where = torch.cuda.get_device_name(trainer.device) if cuda else f"{args.threads} CPU thread(s)"
    print(f"train_step on {source} ({rec.width}x{rec.height}, "
          f"{len(trainer.model.gaussians)} Gaussians), at {args.at:.0%} of {trainer.total_steps} steps, "
          f"{args.steps} steps, {where}, rasterizer {rasterizer}"
          + (", compiled skinning" if args.compile else ""))
    print(f"{'stage':<30}{'ms/step':>10}{'share':>8}" + (f"{'GPU ms':>10}" if cuda else ""))
    for name, ms in sorted(ranges.items(), key=lambda kv: -kv[1]):
        print(f"{name:<30}{ms:>10.2f}{ms / total:>8.0%}" + (f"{gpu.get(name, 0.0):>10.2f}" if cuda else ""))
    rest = total - sum(ranges.values())
    print(f"{'(outside the stages)':<30}{rest:>10.2f}{rest / total:>8.0%}")
    print(f"{'step (profiled)':<30}{total:>10.2f}" + (f"{'':>8}{gpu_total:>10.2f}" if cuda else ""))
    print(f"{'step (median, wall)':<30}{step_ms:>10.2f}")
    if timed:
        print(f"{'step (median, unprofiled)':<30}{timed['median_ms']:>10.2f}   over {args.timed} steps "
              f"(last half {timed['last_half_median_ms']:.2f})")
    per_op = op_cost_us(trainer.device)
    print(f"torch ops per step (not called by another op): {counts['ops']:.0f}"
          + (f"; kernel launches: {counts['launches']:.0f}" if cuda else "")
          + f"; host time to issue one small op: {per_op:.1f} us")
    print(f"\nslowest ops by {'GPU' if cuda else 'self'} time (ms/step):")
    print(f"{'op':<44}{'self ms':>9}{'calls':>7}" + (f"{'GPU ms':>9}" if cuda else ""))
    for row in top:
        print(f"{row['op'][:44]:<44}{row['self_ms']:>9.2f}{row['calls']:>7}"
              + (f"{row['gpu_ms']:>9.3f}" if cuda else ""))
    reads = host_reads(trainer)
    print(f"\nhost reads per step: {reads['per_step']:.1f} ({reads['direct_per_step']:.1f} by project code "
          "itself); by line:")
    for site, n in list(reads["by_site"].items())[:10]:
        print(f"  {n:>7.1f}  {site}")
    syncs = None
    if cuda:
        syncs = cuda_syncs(trainer)
        print(f"CUDA synchronisations per step (torch's count): {syncs['per_step']:.1f}; by line:")
        for site, n in list(syncs["by_site"].items())[:10]:
            print(f"  {n:>7.1f}  {site}")
    load = os.getloadavg()[0]
    print(f"load average {load:.1f} on {os.cpu_count()} CPUs (a shared machine: times are noisy)")
    write_json(args.json, {"source": source, "at": args.at, "steps": args.steps,
                           "device": str(trainer.device), "device_name": where, "threads": args.threads,
                           "rasterizer": rasterizer, "compile": args.compile,
                           "gaussians": len(trainer.model.gaussians),
                           "step_ms_median": step_ms, "step_ms_profiled": total, "timed": timed,
                           "ops_per_step": counts["ops"], "launches_per_step": counts["launches"],
                           "us_per_small_op": per_op,
                           "stages_ms": ranges,
                           "step_gpu_ms": gpu_total, "stages_gpu_ms": gpu, "top_ops": top,
                           "host_reads": reads, "cuda_syncs": syncs, "load_average_1m": load})
    return 0


if __name__ == "__main__":
    sys.exit(main())
