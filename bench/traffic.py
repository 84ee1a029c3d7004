"""The traffic benchmark: the `real` preset on a scene our rasterizer did not draw, trained as a user would.

    .venv/bin/python -m bench.traffic [--out reports] [--steps N] [--variants full,events=false,...]

1. Builds the composited street (``edmcgs synth traffic --fps 5 --seconds 3 --seed 0``: 346x260 grey APS
   frames at 25 Hz with exposure blur and read noise, DAVIS346-like events; every fifth frame an anchor,
   the other 60 held out).
2. Trains each variant with ``edmcgs train REC --config real [--set ...]`` in its own process, one torch
   thread, and measures that process: wall time, CPU time (user + system) and peak resident memory.
3. Scores every checkpoint on the held-out frames through the inference path, beside the trivial
   baselines on the same frames: hold the last anchor, blend the neighbouring anchors, integrate the
   events onto the last anchor, and (a static camera) the anchors' per-pixel median, i.e. the static
   street with every car gone. PSNR over the
   whole frame, SSIM, and PSNR over the moving pixels only (where the frame differs from that median by
   more than ``MOVING``: the cars, about 1 % of the pixels, where between-anchor motion shows).
4. Measures what the full checkpoint leaves out (``bench.report.lean``: frozen points, one channel, one
   pose, against its full twin) and what the static/dynamic split saves: the full model against the same
   preset without the background layer (`bg_layer=false`), deform and render timed alternately.

Writes ``traffic.md``, ``traffic.json`` and ``traffic_frames.png`` (a mid-gap frame: truth, baselines,
variants) into ``--out``; recordings and checkpoints are cached in ``--cache`` by everything that
determines them (timings of a cached run are the ones measured when it was trained).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.results import meets, pick_variants, table, variant_parser, write_json

SCENE_ARGS = ["--fps", "5", "--seconds", "3", "--seed", "0"]
VARIANTS = {"full": [], "markov=false": ["markov=false"], "events=false": ["events=false"],
            "bg_layer=false": ["bg_layer=false"]}
MOVING = 0.06
"""A pixel is moving in a frame where it differs from the anchors' median by more than this (in [0, 1])."""
TARGETS = {
    "train_minutes": ("<=", 15.0),
    "full_minus_blend_db": (">=", 1.0),
    "full_minus_hold_db": (">=", 1.0),
    "full_minus_events_false_db": (">=", 2.0),
}
MEDIAN = "median of the anchors"
"""The static-camera baseline: the anchors' per-pixel median (the street with every car gone)."""


# ------------------------------------------------------------------------------- build and train

def _edmcgs() -> list[str]:
    """The `edmcgs` command of this interpreter's environment."""
    return [sys.executable, "-m", "edmcgs.cli"]


def measured_run(cmd: list[str], log: Path) -> dict:
    """Run ``cmd`` to completion (output to ``log``); its wall and CPU seconds and peak RSS (GB)."""
    started = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}); its output: {log}")
    peak_kb = usage.ru_maxrss  # kilobytes on Linux
    return {"wall_s": time.perf_counter() - started, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_gb": peak_kb / 1e6}


def build_scene(cache: Path) -> Path:
    path = cache / f"traffic_{'_'.join(a.lstrip('-') for a in SCENE_ARGS)}.h5"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".partial.h5")
        measured_run([*_edmcgs(), "synth", "traffic", *SCENE_ARGS, "-q", "-o", str(tmp)], cache / "build.log")
        tmp.replace(path)
    return path


def run_key(rec: Path, overrides: list[str], preset: str = "real", poses: str | None = None) -> str:
    """Everything that determines a run (``bench.report``'s key): the recording, the resolved config and
    where the poses come from."""
    from bench.report.training import run_key as report_key
    from edmcgs.pipeline import build_config, open_recording

    cfg = build_config(preset, overrides, open_recording(rec)).to_dict()
    source = f"{rec.name}:{rec.stat().st_size}" + (f":poses={poses}" if poses else "")
    return report_key(source, cfg, "cpu", False)


def train(rec: Path, name: str, overrides: list[str], cache: Path, preset: str = "real",
          poses: str | None = None) -> dict:
    """Train one variant with ``preset`` in its own process (cached): {name, checkpoint, wall_s, cpu_s,
    peak_gb, ...}. poses: ``edmcgs train --poses`` (``auto``: structure from motion)."""
    key = run_key(rec, overrides, preset, poses)
    ckpt, result = cache / f"{key}.ckpt", cache / f"{key}.json"
    if ckpt.exists() and result.exists():
        return json.loads(result.read_text()) | {"cached": True}
    sets = [a for o in overrides for a in ("--set", o)]
    cache.mkdir(parents=True, exist_ok=True)
    print(f"training {name} ({' '.join(overrides) or f'the {preset} preset as it is'}) ...", file=sys.stderr)
    usage = measured_run([*_edmcgs(), "train", str(rec), "--config", preset, *sets, "--threads", "1", "-q",
                          *(["--poses", poses] if poses else []),
                          "--history", str(cache / f"{key}.csv"), "-o", str(ckpt)], cache / f"{key}.log")
    out = {"name": name, "overrides": overrides, "checkpoint": ckpt.name, "trained_on": platform.node(),
           "trained_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())} | usage
    result.write_text(json.dumps(out, indent=1))
    return out | {"cached": False}


# ------------------------------------------------------------------------------- scores

def _moving_psnr(sq_err: list[float], count: int) -> float:
    return float(10 * np.log10(1.0 / max(sum(sq_err) / max(count, 1), 1e-12)))


def score(data, models: dict, *, static_camera: bool,
          own_poses: bool = False) -> tuple[dict[str, dict], float]:
    """({name: {psnr, ssim, moving_psnr, frames}} of every model and baseline on the same held-out
    frames, the fraction of their pixels that are moving). own_poses: each model renders from its own
    trajectory (poses it estimated: ``data`` has none)."""
    from edmcgs.model.eval.baselines import BASELINES, baseline_image
    from edmcgs.model.eval.evaluation import render_held_out
    from edmcgs.model.eval.metrics import psnr, ssim_score

    median = np.median(data.anchor_images.astype(np.float32) / 255.0, axis=0)
    acc: dict[str, dict] = {}
    moving_px = 0
    for i in data.evaluable().tolist():
        t = int(data.held_out_t_us[i])
        truth = data.held_out_images[i].astype(np.float32) / 255.0
        mask = np.abs(truth - median).max(-1) > MOVING
        moving_px += int(mask.sum())
        images = {name: baseline_image(data, t, name)[0] for name in BASELINES}
        if static_camera:
            images[MEDIAN] = median
        images |= {name: render_held_out(m, data, i, own_poses=own_poses)[0] for name, m in models.items()}
        for name, image in images.items():
            a = acc.setdefault(name, {"psnr": [], "ssim": [], "sq": []})
            a["psnr"].append(psnr(image, truth))
            a["ssim"].append(ssim_score(image, truth))
            a["sq"].append(float(((image - truth) ** 2)[mask].sum()))
    scores = {name: {"psnr": float(np.mean(a["psnr"])), "ssim": float(np.mean(a["ssim"])),
                     "moving_psnr": _moving_psnr(a["sq"], moving_px), "frames": len(a["psnr"])}
              for name, a in acc.items()}
    return scores, moving_px / max(len(data.evaluable()) * median.shape[0] * median.shape[1], 1)


def split_saving(full, layerless, data, *, repeats: int = 5) -> dict:
    """What the background layer saves: deform (mid-gap, with its events) and render ms of the full model
    against the same preset without the layer, timed alternately on the same query, one thread."""
    from bench.report.lean import RENDER_REPEATS, deform_pair_ms, paired_ms
    from bench.report.render import pick_frame

    i = pick_frame(full, data)
    t = int(data.held_out_t_us[i])
    tau = full.tau(t)
    emap = data.event_map(tau, t) if t > tau else None
    deform = deform_pair_ms((full, layerless), t, emap, data, repeats)
    states = [m.deform(t, emap, data.trajectory.at(t)) for m in (full, layerless)]
    render = paired_ms(*[lambda m=m, s=s: m.render(s, data.held_out_pose(i), m.meta.intrinsics, threads=1)
                         for m, s in zip((full, layerless), states, strict=True)], RENDER_REPEATS * repeats)
    return {"gaussians": [len(full.gaussians), len(layerless.gaussians)],
            "control_points": [full.control.num_points, layerless.control.num_points],
            "ms_deform_mid": list(deform), "ms_render": list(render), "t_us": t}


# ------------------------------------------------------------------------------- the report

def frames_figure(data, models: dict, path: Path) -> None:
    """The mid-gap held-out frame farthest from its anchor: truth, baselines and each variant."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.report.render import pick_frame
    from edmcgs.model.eval.baselines import BASELINES, baseline_image
    from edmcgs.model.eval.evaluation import render_held_out

    first = next(iter(models.values()))
    i = pick_frame(first, data)
    t = int(data.held_out_t_us[i])
    panels = [("held-out truth", data.held_out_images[i].astype(np.float32) / 255.0)]
    panels += [(name, baseline_image(data, t, name)[0]) for name in BASELINES]
    panels += [(name, render_held_out(m, data, i)[0]) for name, m in models.items()]
    cols = 3
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for ax, (name, image) in zip(axes.flat, panels, strict=False):
        ax.imshow(np.clip(image[..., 0], 0, 1), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(name, fontsize=9)
    for ax in axes.flat:
        ax.axis("off")
    fig.suptitle(f"traffic, t = {(t - int(data.anchors_t_us[0])) / 1e3:.0f} ms, "
                 f"{(t - first.tau(t)) / 1e3:.0f} ms after its anchor", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown(r: dict, command: str) -> str:
    s, runs = r["scores"], {run["name"]: run for run in r["runs"]}
    lines = ["# Traffic benchmark: the `real` preset on a scene our rasterizer did not draw", "",
             f"`{command}` on {r['machine']}. The scene: {r['scene']}; {r['anchors']} anchors, "
             f"{r['frames']} held-out frames scored. One seed.", "",
             "| held-out frames | PSNR (dB) | SSIM | PSNR on moving pixels | train wall | train CPU "
             "| peak memory |",
             "|---|---|---|---|---|---|---|"]
    for name, row in s.items():
        run = runs.get(name)
        cost = (f"{run['wall_s'] / 60:.1f} min | {run['cpu_s'] / 60:.1f} min | {run['peak_gb']:.2f} GB"
                if run else "— | — | —")
        label = f"{name} (no model)" if run is None else (
            f"`--set {name}`" if VARIANTS[name] else "full model (`--config real`)")
        lines.append(f"| {label} | {row['psnr']:.2f} | {row['ssim']:.3f} | {row['moving_psnr']:.2f} "
                     f"| {cost} |")
    for run in r["runs"]:
        if "measured_by" in run:
            lines.append(f"\n`{run['name']}` was trained at {run['trained_at']}; its cost was measured by "
                         f"{run['measured_by']}.")
    lines += ["", f"Moving pixels: where the held-out frame differs from the anchors' median by more than "
              f"{MOVING:g} (the cars, {100 * r['moving_fraction']:.1f} % of the pixels). Training: "
              "`edmcgs train REC --config real --threads 1`, each variant in its own process (wall time "
              "includes its periodic evaluations; peak memory is that process's resident set).", "",
              "```", table(r["summary"], TARGETS), "```", ""]
    if "split" in r:
        sp = r["split"]
        lines += ["## What the static/dynamic split saves", "",
                  "The background layer holds the static street; the Gaussians are left for what moves. "
                  "Against the same preset without the layer (`--set bg_layer=false`), same query "
                  "(mid-gap, with its events), timed alternately, one thread:", "",
                  "| | Gaussians | control points | deform ms | render ms | checkpoint MB | held-out PSNR |",
                  "|---|---|---|---|---|---|---|"]
        for k, name in enumerate(("full", "bg_layer=false")):
            lines.append(f"| {name} | {sp['gaussians'][k]:,} | {sp['control_points'][k]} | "
                         f"{sp['ms_deform_mid'][k]:.2f} | {sp['ms_render'][k]:.2f} | "
                         f"{sp['bytes'][k] / 1e6:.2f} | {s[name]['psnr']:.2f} |")
        lines.append("")
    if "lean" in r:
        from bench.report.lean import left_out_table, saved_table
        lines += ["## What the full checkpoint leaves out", "",
                  "Against its full twin (same weights, nothing left out: nothing frozen, three channels, "
                  "the whole trajectory), measured by `bench.report.lean`:", "",
                  *left_out_table([r["lean"]]), "", *saved_table([r["lean"]]), ""]
    lines += ["![a mid-gap frame](traffic_frames.png)", ""]
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    return variant_parser("traffic", __doc__, VARIANTS, "another recording instead of the street")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    names = pick_variants(args.variants, VARIANTS, "bench.traffic")
    import torch

    from bench.report.lean import measure
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.eval.baselines import BASELINES
    from edmcgs.pipeline import open_recording, training_data
    torch.set_num_threads(1)

    rec_path = args.recording or build_scene(args.cache)
    steps = [] if args.steps is None else [f"iterations={args.steps}"]
    runs = [train(rec_path, name, steps + VARIANTS[name], args.cache) for name in names]
    data = training_data(open_recording(rec_path))
    models = {run["name"]: load_checkpoint(args.cache / run["checkpoint"]) for run in runs}
    static = all(m.meta.lean["static_camera"]["value"] for m in models.values())
    scores, moving = score(data, models, static_camera=static)
    baselines = {k: v for k, v in scores.items() if k not in models}
    scores = {k: scores[k] for k in [*models, *baselines]}
    scene = (f"`{rec_path}`" if args.recording else
             f"`edmcgs synth traffic {' '.join(SCENE_ARGS)}` (composited in 2D, not Gaussians; 346x260 grey, "
             "exposure blur, read noise, DAVIS346-like events; anchors at 5 fps)")
    r = {"machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "recording": str(rec_path),
         "scene": scene, "anchors": len(data.anchors_t_us), "frames": len(data.evaluable()),
         "moving_fraction": float(moving),
         "runs": runs, "scores": scores}
    summary = {}
    if "full" in models:
        full = runs[names.index("full")]
        summary |= {"train_minutes": full["wall_s"] / 60, "train_cpu_minutes": full["cpu_s"] / 60,
                    "peak_memory_gb": full["peak_gb"],
                    "full_minus_blend_db": scores["full"]["psnr"] - scores[BASELINES[1]]["psnr"],
                    "full_minus_hold_db": scores["full"]["psnr"] - scores[BASELINES[0]]["psnr"],
                    "full_minus_integrate_db": scores["full"]["psnr"] - scores[BASELINES[2]]["psnr"],
                    "full_minus_median_db": scores["full"]["psnr"] - scores[MEDIAN]["psnr"]}
        if "events=false" in models:
            summary["full_minus_events_false_db"] = scores["full"]["psnr"] - scores["events=false"]["psnr"]
        r["lean"] = measure("traffic, full", args.cache / full["checkpoint"], data, repeats=3)
        if "bg_layer=false" in models:
            sizes = [(args.cache / runs[names.index(n)]["checkpoint"]).stat().st_size
                     for n in ("full", "bg_layer=false")]
            r["split"] = split_saving(models["full"], models["bg_layer=false"], data) | {"bytes": sizes}
    r["summary"] = summary
    r["targets_met"] = {k: meets(v, TARGETS[k]) for k, v in summary.items() if k in TARGETS}
    args.out.mkdir(parents=True, exist_ok=True)
    frames_figure(data, models, args.out / "traffic_frames.png")
    command = "python -m bench.traffic" + (f" {' '.join(argv)}" if argv else "")
    (args.out / "traffic.md").write_text(markdown(r, command))
    write_json(args.out / "traffic.json", r)
    write_json(args.json, r)
    print(table(summary, TARGETS))
    print(f"wrote {args.out / 'traffic.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
