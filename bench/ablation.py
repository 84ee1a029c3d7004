"""EdMCGS ablations on one recording: train each variant, score it on the held-out frames.

    .venv/bin/python -m bench.ablation RECORDING [--config demo] [--variants full,events=false,...]
        [--set KEY=VALUE ...] [--out DIR] [--json PATH]

A variant is ``full`` or comma-free ``key=value`` switches joined by ``+`` (e.g. ``events=false``,
``markov=false``, ``local_sampling=false``, ``tli=false``). Every variant trains from the same preset
and seed on one torch thread; the table gives held-out PSNR / SSIM (mean over frames), the training
time and its difference from ``full``. Wall-clock times are noisy on a shared machine.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np
import torch
from edmcgs.model.edmcgs import EdMCGS
from edmcgs.model.evaluation import evaluate, summarize
from edmcgs.model.trainer import Trainer, write_history_csv
from edmcgs.sensor.recording import read_recording

from edmcgs.train_cli import build_config, training_data

DEFAULT_VARIANTS = "full,events=false,markov=false"


def run_variant(rec, data, preset_name: str, overrides: list[str], out: Path, name: str) -> dict:
    cfg = build_config(preset_name, overrides, rec)
    model = EdMCGS.from_arrays(anchors_t_us=data.anchors_t_us, anchor_images=data.anchor_images,
                               intrinsics=data.intrinsics, anchor_poses=data.anchor_poses,
                               t_end_us=data.t_end_us, trajectory=data.trajectory, event_size=data.event_size,
                               config=cfg)
    started = time.perf_counter()
    trainer = Trainer(model, data, progress=True)
    history = trainer.fit(out / f"{name}.ckpt")
    seconds = time.perf_counter() - started
    write_history_csv(history, out / f"{name}_history.csv")
    rows = evaluate(trainer.model, data)
    with open(out / f"{name}_frames.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["index", "t_us", "anchor_us", "events", "psnr", "ssim"])
        for r in rows:
            writer.writerow([r.index, r.t_us, r.anchor_us, r.events, f"{r.psnr:.4f}", f"{r.ssim:.5f}"])
    summary = summarize(rows)
    return {"variant": name, "overrides": overrides, "psnr": summary["psnr"], "ssim": summary["ssim"],
            "frames": summary["frames"], "train_seconds": round(seconds, 1),
            "iterations": cfg.iterations, "gaussians": len(trainer.model.gaussians)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench.ablation", description=__doc__.splitlines()[0])
    p.add_argument("recording")
    p.add_argument("--config", default="demo")
    p.add_argument("--variants", default=DEFAULT_VARIANTS)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", default="reports/ablation")
    p.add_argument("--json")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = read_recording(args.recording)
    data = training_data(rec)
    results = []
    for variant in args.variants.split(","):
        switches = [] if variant == "full" else variant.split("+")
        name = variant.replace("=", "-").replace("+", "_")
        results.append(run_variant(rec, data, args.config, [*args.overrides, *switches], out, name))
        last = results[-1]
        print(f"{variant}: PSNR {last['psnr']:.2f} dB in {last['train_seconds']:.0f} s", flush=True)
    full = next((r for r in results if r["variant"] == "full"), None)
    print(f"\n{args.recording}, config {args.config} {' '.join(args.overrides)}\n")
    print("| variant | PSNR (dB) | SSIM | vs full (dB) | train time (s) | Gaussians |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in results:
        delta = "" if full is None or r is full else f"{r['psnr'] - full['psnr']:+.2f}"
        print(f"| {r['variant']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {delta} | {r['train_seconds']:.0f} "
              f"| {r['gaussians']} |")
    payload = {"recording": str(args.recording), "config": args.config, "overrides": args.overrides,
               "results": results, "torch_threads": args.threads, "numpy": np.__version__}
    (out / "ablation.json").write_text(json.dumps(payload, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(payload, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
