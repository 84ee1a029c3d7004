"""Rasterizer benchmark: the fast numba path (forward) and the differentiable torch path (forward +
backward) at 173x130 and 346x260 with 2k, 8k and 20k Gaussians in view.

    .venv/bin/python -m bench.render [--json PATH] [--runs N] [--threads T]

The scene: N Gaussians whose centres are spread uniformly over the image at depths 2-6 m, random
orientations, per-axis scales giving a screen sigma log-uniform in 0.7-4 px at 346x260 (3-sigma
radius ~2-12 px; half that at 173x130, which renders the same scene), opacities U(0.2, 0.95),
degree-3 SH colours. Each configuration runs in a fresh subprocess (so its peak RSS, the process's
ru_maxrss including the interpreter and imports, is its own), warms up, then times ``--runs`` calls;
the rows give the median and 90th percentile wall time. ``--threads`` sets torch's and numba's
thread counts in the children (default: theirs, all cores). Timings are wall clock on a shared
machine: the load average is printed with the table.
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

from bench.results import write_json

SIZES = ((173, 130), (346, 260))
COUNTS = (2000, 8000, 20000)
WARMUP = 3
FIELDS = ("means", "quats", "scales", "opacities", "colors")


def _scene(n: int, width: int, height: int):
    from tests.support.scenes import random_scene

    scene = random_scene(n, 346, 260, seed=n, sh_degree=3, px_sigma=(0.7, 4.0), margin=0.0)
    scene["intrinsics"] = scene["intrinsics"].scaled(width, height)
    return scene


def _time(step, runs: int) -> list[float]:
    for _ in range(WARMUP):
        step()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return times


def measure(path: str, width: int, height: int, n: int, runs: int, threads: int | None) -> dict:
    """One row, measured in this process."""
    import numba
    import torch

    if threads:
        torch.set_num_threads(threads)
        numba.set_num_threads(threads)
    scene = _scene(n, width, height)
    if path == "fast":
        from edmcgs.model.render.rasterize_fast import rasterize_fast

        arrays = [scene[k].astype(np.float32) for k in FIELDS]

        def step():
            rasterize_fast(*arrays, scene["w2c"], scene["intrinsics"])
    else:
        from edmcgs.model.render.rasterize import rasterize

        params = [torch.tensor(scene[k], dtype=torch.float32, requires_grad=True) for k in FIELDS]

        def step():
            for p in params:
                p.grad = None
            out = rasterize(*params, scene["w2c"], scene["intrinsics"])
            out.image.sum().backward()
    times = np.array(_time(step, runs)) * 1e3
    return {"path": path, "width": width, "height": height, "gaussians": n,
            "median_ms": round(float(np.median(times)), 2),
            "p90_ms": round(float(np.percentile(times, 90)), 2),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
            "threads": torch.get_num_threads()}


def _in_subprocess(path: str, width: int, height: int, n: int, runs: int, threads: int | None) -> dict:
    cmd = [sys.executable, "-m", "bench.render", "--one", path, str(width), str(height), str(n),
           "--runs", str(runs)] + (["--threads", str(threads)] if threads else [])
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=root)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the rows here as a JSON list")
    parser.add_argument("--runs", type=int, default=20, help="timed runs per configuration (>= 10)")
    parser.add_argument("--threads", type=int, help="torch and numba threads (default: all cores)")
    parser.add_argument("--one", nargs=4, metavar=("PATH", "W", "H", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.runs < 10:
        parser.error("--runs must be >= 10")
    if args.one:
        path, w, h, n = args.one
        print(json.dumps(measure(path, int(w), int(h), int(n), args.runs, args.threads)))
        return 0

    from tqdm import tqdm

    configs = [(p, w, h, n) for p in ("fast", "autograd") for w, h in SIZES for n in COUNTS]
    load_before = os.getloadavg()
    rows = [_in_subprocess(*c, args.runs, args.threads)
            for c in tqdm(configs, desc="render bench", unit="config")]
    load_after = os.getloadavg()
    print(f"\nscene: Gaussians spread over the view, 3-sigma radius ~2-12 px at 346x260, SH degree 3; "
          f"{args.runs} timed runs after {WARMUP} warm-up, one subprocess per row")
    print(f"fast = rasterize_fast forward; autograd = rasterize forward + backward; {os.cpu_count()} CPUs, "
          f"{rows[0]['threads']} threads, load average {load_before[0]:.2f} before, "
          f"{load_after[0]:.2f} after")
    print(f"{'path':<9} {'size':>8} {'gaussians':>9} {'median ms':>10} {'p90 ms':>8} {'peak RSS MB':>12}")
    for r in rows:
        print(f"{r['path']:<9} {r['width']:>4}x{r['height']:<3} {r['gaussians']:>9} {r['median_ms']:>10.2f} "
              f"{r['p90_ms']:>8.2f} {r['peak_rss_mb']:>12.1f}")
    write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
