"""Training runs for the report: held-out error against training time, one run per (scene, rate, variant).

The model's own ``Trainer`` does the work; this loop only times ``train_step`` alone and evaluates at
fixed steps outside the clock, so every variant is on the same time axis (seconds of training, on the
report's thread count, evaluation excluded). ``Trainer.fit`` then finishes the run as usual (its loop
has nothing left to do). Results and checkpoints are cached by everything that determines them.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from edmcgs.model.checkpoint import load_checkpoint, save_checkpoint
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.eval.evaluation import evaluate, summarize
from edmcgs.model.eval.lpips import LPIPS
from edmcgs.model.train.trainer import Trainer
from edmcgs.pipeline import build_config, new_model, training_data
from edmcgs.sensor.files.recording import Recording


def _overrides(switches: dict, iterations: int, train_scale: float | None) -> list[str]:
    items = [f"iterations={iterations}", "eval_every=0", "checkpoint_every=0"]
    items += [] if train_scale is None else [f"train_scale={train_scale}"]
    return items + [f"{k}={str(v).lower()}" for k, v in switches.items()]


def run_key(rec_key: str, config: dict, device: str, lpips: bool) -> str:
    # The resolved config, not the preset's name: a retuned preset must not reuse an older run. Keys
    # sorted: the same values are the same run, whatever order the config lists its fields in.
    blob = json.dumps([rec_key, config, device, torch.get_num_threads(), torch.__version__]
                      + (["lpips"] if lpips else []), sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]


def train_run(rec: Recording, rec_key: str, switches: dict, *, preset: str, iterations: int,
              train_scale: float | None, curve_points: int, device: str, cache: Path, label: str,
              progress: bool = True, lpips: LPIPS | None = None) -> dict:
    """Train one variant; returns {curve, psnr, ssim, lpips, frames, train_seconds, ..., checkpoint}
    (cached). LPIPS is scored at the end when ``lpips`` is given (else None)."""
    overrides = _overrides(switches, iterations, train_scale)
    cfg = build_config(preset, overrides, rec)
    key = run_key(rec_key, cfg.to_dict(), device, lpips is not None)
    result_path, ckpt_path = cache / f"{key}.json", cache / f"{key}.ckpt"
    if result_path.exists() and ckpt_path.exists():
        return json.loads(result_path.read_text()) | {"cached": True}
    cache.mkdir(parents=True, exist_ok=True)
    data = training_data(rec)
    model = new_model(data, cfg)
    started = time.perf_counter()
    trainer = Trainer(model, data, device=device, progress=False)
    setup_seconds = time.perf_counter() - started
    checkpoints = set(np.unique(np.linspace(0, iterations, curve_points + 1).round().astype(int)).tolist())
    curve, train_seconds, eval_seconds, nonfinite = [], 0.0, 0.0, 0

    def checkpoint() -> None:
        nonlocal eval_seconds
        t0 = time.perf_counter()
        scores = trainer.evaluate()
        eval_seconds += time.perf_counter() - t0
        curve.append({"step": trainer.step, "seconds": train_seconds, "psnr": scores["psnr"],
                      "ssim": scores["ssim"], "gaussians": len(trainer.model.gaussians)})

    with tqdm(total=iterations, desc=label, disable=not progress, dynamic_ncols=True, leave=False) as bar:
        checkpoint()
        while trainer.step < iterations:
            t0 = time.perf_counter()
            losses = trainer.train_step()
            train_seconds += time.perf_counter() - t0
            nonfinite += not all(math.isfinite(v) for v in losses.values())
            bar.update(1)
            if trainer.step in checkpoints:
                checkpoint()
                bar.set_postfix(psnr=f"{curve[-1]['psnr']:.2f}", refresh=False)
    trainer.fit()  # nothing left to train: the usual end of a run (full event scale, eval mode)
    t0 = time.perf_counter()
    rows = evaluate(trainer.model, data, lpips=lpips)
    final_eval_seconds = time.perf_counter() - t0
    summary = summarize(rows)
    save_checkpoint(trainer.model, ckpt_path)
    result = {
        "key": key, "recording": rec_key, "preset": preset, "overrides": overrides, "device": device,
        "threads": torch.get_num_threads(), "iterations": iterations, "setup_seconds": setup_seconds,
        "train_seconds": train_seconds, "eval_seconds": eval_seconds,
        "final_eval_seconds": final_eval_seconds,
        "nonfinite_steps": nonfinite, "gaussians": len(trainer.model.gaussians),
        "control_points": trainer.model.control.num_points, "psnr": summary["psnr"], "ssim": summary["ssim"],
        "ssim_3dgs": summary.get("ssim_3dgs"), "lpips": summary.get("lpips"), "frames": summary["frames"],
        "curve": curve,
        "checkpoint": ckpt_path.name,
        "per_frame": [{"index": r.index, "t_us": r.t_us, "anchor_us": r.anchor_us, "events": r.events,
                       "psnr": r.psnr, "ssim": r.ssim, "ssim_3dgs": r.ssim_3dgs, "lpips": r.lpips}
                      for r in rows],
    }
    result_path.write_text(json.dumps(result, indent=1))
    return result | {"cached": False}


def load_run_model(result: dict, cache: Path, device: str = "cpu") -> EdMCGS:
    """The trained model of a ``train_run`` result."""
    return load_checkpoint(cache / result["checkpoint"], device=device)


def _train_job(job: dict) -> dict:
    """A Ray task's body: one ``train_run`` (its result also lands in the cache, as a sequential run's)."""
    return train_run(**job)


def train_on_ray(jobs: list[dict], *, threads: int, num_cpus: int | None = None) -> list[dict]:
    """``train_run(**job)`` for every job as Ray tasks, ``threads`` CPUs each (``edmcgs.fanout``); the
    cache key holds the thread count, so the driver (at the same ``--threads``) then finds every run
    cached."""
    from edmcgs.fanout import fan_out

    return fan_out(_train_job, [{**job, "progress": False} for job in jobs], threads=threads,
                   num_cpus=num_cpus)
