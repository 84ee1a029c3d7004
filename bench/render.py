"""Rasterizer benchmark: the fast numba forward (``rasterize_fast``, serving) and the differentiable
``rasterize`` forward + backward on both of its CPU paths, torch and numba (training on the CPU), at
173x130 and 346x260 with 2k, 8k and 20k Gaussians in view; with ``--device cuda``, ``rasterize``'s CUDA
paths (torch, and gsplat where installed), forward alone and forward + backward.

    .venv/bin/python -m bench.render [--json PATH] [--runs N] [--threads T] [--paths fast,torch,numba]
        [--device cpu|cuda] [--sizes 346x260] [--counts 8000]
    .venv/bin/python -m bench.render --profile numba|torch|gsplat [--threads T] [--device cpu|cuda]

The scene: N Gaussians whose centres are spread uniformly over the image at depths 2-6 m, random
orientations, per-axis scales giving a screen sigma log-uniform in 0.7-4 px at 346x260 (3-sigma
radius ~2-12 px; half that at 173x130, which renders the same scene), opacities U(0.2, 0.95),
degree-3 SH colours. Each configuration runs in a fresh subprocess (so its peak RSS, the process's
ru_maxrss including the interpreter and imports, is its own), warms up, then times ``--runs`` calls;
the rows give the median and 90th percentile wall time and the median CPU time of the process
(what a preempted run on a loaded machine does not inflate). ``--threads`` sets torch's and numba's
thread counts in the children (default: theirs, all cores). Timings are wall clock on a shared
machine: the load average is printed with the table, then the targets (fwd+bwd at 8k Gaussians,
the fast forward at 346x260) and the torch / numba ratio of the training paths. On CUDA each timed call
ends with ``torch.cuda.synchronize()`` (the time the GPU took, not only the launches), the CPU column is
the host's, and the targets are the GPU's (346x260, 8k Gaussians: forward <= 1 ms, with backward <= 3).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.results import table, write_json

SIZES = ((173, 130), (346, 260))
COUNTS = (2000, 8000, 20000)
PATHS = ("fast", "torch", "numba")
CUDA_PATHS = ("torch", "gsplat")
WARMUP = 3
FIELDS = ("means", "quats", "scales", "opacities", "colors")
TARGETS = {"numba_fwd_bwd_173x130_8k_ms": ("<=", 25.0), "numba_fwd_bwd_346x260_8k_ms": ("<=", 60.0)}
FAST_TARGET = {1: ("<=", 5.0), 2: ("<=", 3.2)}
"""The fast forward at 346x260 with 8k Gaussians, by thread count (the issue's targets)."""
CUDA_TARGETS = {"fwd": ("<=", 1.0), "fwd_bwd": ("<=", 3.0)}
"""A CUDA path at 346x260 with 8k Gaussians, by pass."""


def _scene(n: int, width: int, height: int):
    from harness.scenes import random_scene

    scene = random_scene(n, 346, 260, seed=n, sh_degree=3, px_sigma=(0.7, 4.0), margin=0.0)
    scene["intrinsics"] = scene["intrinsics"].scaled(width, height)
    return scene


def _time(step, runs: int) -> tuple[list[float], list[float]]:
    """(wall, CPU) seconds of each timed run."""
    for _ in range(WARMUP):
        step()
    wall, cpu = [], []
    for _ in range(runs):
        start, start_cpu = time.perf_counter(), time.process_time()
        step()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return wall, cpu


def _step(path: str, scene: dict, device: str, backward: bool):
    """One call of ``path`` on ``scene`` (a CUDA call waits for the device before it returns)."""
    import torch

    if path == "fast":
        from edmcgs.model.render.rasterize_fast import rasterize_fast

        arrays = [scene[k].astype(np.float32) for k in FIELDS]
        return lambda: rasterize_fast(*arrays, scene["w2c"], scene["intrinsics"])
    from edmcgs.model.render.rasterize import rasterize

    params = [torch.tensor(scene[k], dtype=torch.float32, device=device, requires_grad=backward)
              for k in FIELDS]
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def step():
        for p in params:
            p.grad = None
        with torch.set_grad_enabled(backward):
            out = rasterize(*params, scene["w2c"], scene["intrinsics"], backend=path)
            if backward:
                out.image.sum().backward()
        sync()
    return step


def measure(path: str, width: int, height: int, n: int, runs: int, threads: int | None,
            device: str = "cpu") -> list[dict]:
    """Rows measured in this process: on the CPU one (the fast forward, or a training path's forward +
    backward); on CUDA the forward alone and the forward + backward."""
    import numba
    import torch

    if threads:
        torch.set_num_threads(threads)
        numba.set_num_threads(threads)
    scene = _scene(n, width, height)
    passes = ("fwd", "fwd_bwd") if device == "cuda" else ("fwd" if path == "fast" else "fwd_bwd",)
    rows = []
    for kind in passes:
        wall, cpu = _time(_step(path, scene, device, kind == "fwd_bwd"), runs)
        times = np.array(wall) * 1e3
        rows.append({"path": path, "pass": kind, "device": device, "width": width, "height": height,
                     "gaussians": n, "median_ms": round(float(np.median(times)), 3),
                     "p90_ms": round(float(np.percentile(times, 90)), 3),
                     "cpu_median_ms": round(float(np.median(cpu)) * 1e3, 3),
                     "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                     "threads": torch.get_num_threads()})
    return rows


def profile(path: str, width: int, height: int, n: int, runs: int, threads: int | None,
            device: str = "cpu") -> str:
    """The stages of ``runs`` forward + backward passes of ``rasterize`` on ``path``, by self time (torch
    profiler: the wall time of each op on its thread, so a loaded machine inflates it):
    the autograd Functions (``ProjectFast``, ``ShColorFast``, ``CompositeFast`` and their backwards
    on the numba path) and the torch ops around them. On CUDA also each op's self time on the GPU
    (its kernels), and the rows are sorted by it."""
    import numba
    import torch
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    if threads:
        torch.set_num_threads(threads)
        numba.set_num_threads(threads)
    step = _step(path, _scene(n, width, height), device, backward=True)
    for _ in range(WARMUP):
        step()
    cuda = device == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with torch_profile(activities=activities) as prof:
        for _ in range(runs):
            step()
    events = prof.key_averages()
    head = (f"\n{path} forward + backward on {device}, {width}x{height}, {n} Gaussians, {runs} runs "
            "(ms per run)")

    def gpu(e) -> float:
        return getattr(e, "self_device_time_total", 0.0) / runs / 1e3

    rows = sorted(events, key=lambda e: -(gpu(e) if cuda else e.self_cpu_time_total))[:15]
    total = sum(e.self_cpu_time_total for e in events) / runs / 1e3
    lines = [head, f"{'stage':<40} {'self ms':>12} {'calls':>6}" + (f" {'GPU ms':>9}" if cuda else "")]
    lines += [f"{e.key[:40]:<40} {e.self_cpu_time_total / runs / 1e3:>12.2f} {e.count // runs:>6}"
              + (f" {gpu(e):>9.3f}" if cuda else "") for e in rows]
    lines.append(f"{'all stages':<40} {total:>12.2f}" + (f" {sum(gpu(e) for e in events):>16.3f}"
                                                         if cuda else ""))
    return "\n".join(lines)


def _in_subprocess(path: str, width: int, height: int, n: int, runs: int, threads: int | None,
                   device: str) -> list[dict]:
    cmd = [sys.executable, "-m", "bench.render", "--one", path, str(width), str(height), str(n),
           "--runs", str(runs), "--device", device] + (["--threads", str(threads)] if threads else [])
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=root)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _sizes(text: str) -> list[tuple[int, int]]:
    out = []
    for item in text.split(","):
        w, _, h = item.strip().lower().partition("x")
        out.append((int(w), int(h)))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the rows here as a JSON list")
    parser.add_argument("--runs", type=int, default=20, help="timed runs per configuration (>= 10)")
    parser.add_argument("--threads", type=int, help="torch and numba threads (default: all cores)")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="cpu (default): the paths fast, torch, numba; cuda: torch and gsplat")
    parser.add_argument("--paths", help="comma-separated subset of the device's paths (default: all; on "
                                        "cuda gsplat only where it is installed)")
    parser.add_argument("--sizes", type=_sizes, default=list(SIZES),
                        help="comma-separated WxH (default: 173x130,346x260)")
    parser.add_argument("--counts", type=lambda t: [int(v) for v in t.split(",")], default=list(COUNTS),
                        help="comma-separated Gaussian counts (default: 2000,8000,20000)")
    parser.add_argument("--profile", choices=("torch", "numba", "gsplat"),
                        help="instead of the table: the per-stage time of one training path's "
                             "forward + backward at each size with 8k Gaussians (torch.profiler)")
    parser.add_argument("--one", nargs=4, metavar=("PATH", "W", "H", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.runs < 10:
        parser.error("--runs must be >= 10")
    if args.device == "cuda":
        from edmcgs.errors import InvalidInputError
        from edmcgs.model.devices import check_device
        from edmcgs.model.render.rasterize_gsplat import available

        try:
            check_device("cuda")
        except InvalidInputError as exc:
            parser.error(str(exc))
        known = CUDA_PATHS
        default = [p for p in CUDA_PATHS if p != "gsplat" or available()]
    else:
        known = default = PATHS
    paths = default if args.paths is None else [p for p in args.paths.split(",") if p]
    if not paths or any(p not in known for p in paths):
        parser.error(f"--paths must name some of {', '.join(known)} on {args.device}, got {args.paths!r}")
    if args.profile:
        for w, h in args.sizes:
            print(profile(args.profile, w, h, 8000, args.runs, args.threads, args.device))
        return 0
    if args.one:
        path, w, h, n = args.one
        print(json.dumps(measure(path, int(w), int(h), int(n), args.runs, args.threads, args.device)))
        return 0

    from tqdm import tqdm

    configs = [(p, w, h, n) for p in paths for w, h in args.sizes for n in args.counts]
    load_before = os.getloadavg()
    rows = [row for c in tqdm(configs, desc="render bench", unit="config")
            for row in _in_subprocess(*c, args.runs, args.threads, args.device)]
    load_after = os.getloadavg()
    print(f"\nscene: Gaussians spread over the view, 3-sigma radius ~2-12 px at 346x260, SH degree 3; "
          f"{args.runs} timed runs after {WARMUP} warm-up, one subprocess per configuration")
    if args.device == "cuda":
        import torch

        print(f"on {torch.cuda.get_device_name()}: rasterize's CUDA paths, forward (fwd) and forward + "
              f"backward (fwd_bwd), each run waited for; load average {load_before[0]:.2f} before, "
              f"{load_after[0]:.2f} after")
    else:
        print(f"fast = rasterize_fast forward; torch / numba = rasterize forward + backward on that path; "
              f"{os.cpu_count()} CPUs, {rows[0]['threads']} threads, load average {load_before[0]:.2f} "
              f"before, {load_after[0]:.2f} after")
    print(f"{'path':<9} {'pass':<8} {'size':>8} {'gaussians':>9} {'median ms':>10} {'p90 ms':>8} "
          f"{'CPU ms':>8} {'peak RSS MB':>12}")
    for r in rows:
        print(f"{r['path']:<9} {r['pass']:<8} {r['width']:>4}x{r['height']:<3} {r['gaussians']:>9} "
              f"{r['median_ms']:>10.3f} {r['p90_ms']:>8.3f} {r['cpu_median_ms']:>8.2f} "
              f"{r['peak_rss_mb']:>12.1f}")
    summary, targets = _summary(rows) if args.device == "cpu" else _summary_cuda(rows)
    print("\n" + table(summary, targets))
    write_json(args.json, {"device": args.device, "rows": rows, "summary": summary})
    return 0


def _summary(rows: list[dict]) -> tuple[dict, dict]:
    """The targeted medians (and CPU medians) and the torch / numba ratios of the training paths."""
    by = {(r["path"], r["width"], r["height"], r["gaussians"]): r for r in rows}
    summary, targets = {}, dict(TARGETS)
    for w, h in SIZES:
        for n in COUNTS:
            torch_row, numba_row = by.get(("torch", w, h, n)), by.get(("numba", w, h, n))
            size = f"{w}x{h}_{n // 1000}k"
            if numba_row:
                summary[f"numba_fwd_bwd_{size}_ms"] = numba_row["median_ms"]
                summary[f"numba_fwd_bwd_{size}_cpu_ms"] = numba_row["cpu_median_ms"]
            if torch_row:
                summary[f"torch_fwd_bwd_{size}_ms"] = torch_row["median_ms"]
                summary[f"torch_fwd_bwd_{size}_cpu_ms"] = torch_row["cpu_median_ms"]
            if torch_row and numba_row:
                summary[f"torch_over_numba_{size}"] = round(
                    torch_row["median_ms"] / numba_row["median_ms"], 2)
                summary[f"torch_over_numba_{size}_cpu"] = round(
                    torch_row["cpu_median_ms"] / numba_row["cpu_median_ms"], 2)
    fast = by.get(("fast", 346, 260, 8000))
    if fast:
        summary["fast_346x260_8k_ms"] = fast["median_ms"]
        if fast["threads"] in FAST_TARGET:
            targets["fast_346x260_8k_ms"] = FAST_TARGET[fast["threads"]]
    return summary, targets


def _summary_cuda(rows: list[dict]) -> tuple[dict, dict]:
    """Every CUDA row's median by path, pass and size; the 346x260 8k ones against the GPU targets."""
    summary, targets = {}, {}
    for r in rows:
        key = f"{r['path']}_{r['pass']}_{r['width']}x{r['height']}_{r['gaussians'] // 1000}k_ms"
        summary[key] = r["median_ms"]
        if (r["width"], r["height"], r["gaussians"]) == (346, 260, 8000):
            targets[key] = CUDA_TARGETS[r["pass"]]
    return summary, targets


if __name__ == "__main__":
    raise SystemExit(main())
