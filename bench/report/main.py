"""The accuracy, speed and stability report: CSV, PNG plots and a Markdown summary in ``reports/``.

    .venv/bin/python -m bench.report [--full] [--out reports/] [--scenes a,b] [--fps 5,10]
        [--variants full,no_events,...] [--iterations N] [--threads 1] [--device cpu] [--ray]

The default is small (one scene, 1 s, 200 steps per run: about 10 minutes on a shared 2-core CPU);
``--full`` is the paper's grid (four scenes at 5 and 10 fps, every ablation, 3000 steps per run: hours
on a CPU). Built recordings and trained runs are cached under ``OUT/cache``, so a second run only redoes
what changed. Sections: the ablation table (with the paper's averages beside it), held-out error against
training time, render error against time per frame over the fast path's knobs, the stability cases too
slow for the test suite, what each checkpoint leaves out (measured against its full twin, with a grey
variant of the first scene: one more training run), and the full model served past its span with online
anchors (a recording of the first scene four times as long). Run it from the repository root: the render
sweep uses the float64 reference renderer in bench/. ``--ray`` trains all the report's runs (the grid, the
sparse rates, the lean section's) as Ray tasks side by side (``--threads`` CPUs each, the 'ray' extra;
RAY_ADDRESS joins a cluster), into the same cache; the rest of the report then runs as without it.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import sys
import time
from pathlib import Path

import numba
import torch
from tqdm import tqdm

from bench.online import online_drift
from bench.report.baselines import baseline_rows
from bench.report.data import scene_recordings
from bench.report.lean import event_branch_ms, grey_recording, lean_rows, median_threshold, refrozen
from bench.report.lean import section as lean_section
from bench.report.markdown import summary
from bench.report.online import long_recording, online_rows
from bench.report.online import section as online_section
from bench.report.plots import ablation_bars, error_vs_time, render_knobs
from bench.report.render import render_sweep
from bench.report.settings import FULL, SMALL, VARIANTS, ReportSettings
from bench.report.stability import (
    TEST_CASES,
    event_window_rows,
    pose_rows,
    precision_rows,
    sparse_anchor_rows,
)
from bench.report.training import load_run_model, train_on_ray, train_run
from bench.results import run_info
from edmcgs.atomic import atomic_output
from edmcgs.model.eval.lpips import LPIPS, find_weights
from edmcgs.pipeline import training_data

log = logging.getLogger("bench.report")

DAY_US = 86_400_000_000


def write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _csv_list(text: str, cast=str) -> tuple:
    return tuple(cast(v.strip()) for v in text.split(",") if v.strip())


def settings_from(args) -> ReportSettings:
    s = FULL if args.full else SMALL
    if args.scenes:
        s = s.replace(scenes=_csv_list(args.scenes))
    if args.fps:
        s = s.replace(fps=_csv_list(args.fps, float))
    if args.variants:
        unknown = set(_csv_list(args.variants)) - set(VARIANTS)
        if unknown:
            raise SystemExit(f"--variants: unknown {sorted(unknown)}; choose from {', '.join(VARIANTS)}")
        s = s.replace(variants=_csv_list(args.variants))
    if args.iterations:
        s = s.replace(iterations=args.iterations)
    return s


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench.report", description=__doc__.splitlines()[0])
    p.add_argument("--full", action="store_true", help="the paper's grid (hours on a CPU)")
    p.add_argument("--out", type=Path, default=Path("reports"), help="output folder (default reports/)")
    p.add_argument("--scenes", help="comma-separated scenes (default: the setting's)")
    p.add_argument("--fps", help="comma-separated anchor rates (default 5,10)")
    p.add_argument("--variants", help=f"comma-separated variants among {', '.join(VARIANTS)}")
    p.add_argument("--iterations", type=int, help="training steps per run")
    p.add_argument("--threads", type=int, default=1, help="torch and numba threads (default 1)")
    p.add_argument("--device", default="cpu", help="torch device for training (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--ray", action="store_true",
                   help="train every run of the report as Ray tasks side by side")
    p.add_argument("--ray-cpus", type=int, metavar="N", help="CPUs of the local Ray --ray starts")
    return p


def collect(s: ReportSettings, cache: Path, *, device: str, progress: bool,
            ray: tuple[int, int | None] | None = None) -> dict:
    """Build the recordings, train every run, sweep the render knobs, measure the stability cases."""
    first = s.scenes[0]
    recs = {}
    for scene in s.scenes:
        rates = set(s.fps) | (set(s.sparse_fps) if scene == first else set())
        recs[scene] = scene_recordings(scene, sorted(rates), s, cache / "recordings", progress=progress)

    weights = find_weights()  # LPIPS only on weights already on disk (see edmcgs.model.eval.lpips)
    lpips = None if weights is None else LPIPS.load(*weights).to(device)

    def job(scene: str, fps: float, variant: str, source: tuple | None = None) -> dict:
        rec, key = recs[scene][fps] if source is None else source  # (recording, cache key)
        return dict(rec=rec, rec_key=key, switches=VARIANTS[variant][0], preset=s.preset,
                    iterations=s.iterations, train_scale=s.train_scale, curve_points=s.curve_points,
                    device=device, cache=cache / "runs", label=f"{scene} {fps:g} fps {variant}",
                    progress=progress, lpips=lpips)

    def run(scene: str, fps: float, variant: str, source: tuple | None = None) -> dict:
        result = train_run(**job(scene, fps, variant, source))
        if ray is not None and not result["cached"]:  # planned_runs missed it: trained here, one at a time
            log.warning("bench.report --ray: %s %g fps %s was not among the runs trained on Ray", scene, fps,
                        variant)
        return {"scene": scene, "fps": fps, "variant": variant, **result}

    grid = [(scene, fps, v) for scene in s.scenes for fps in s.fps for v in s.variants]
    if ray is not None:  # every run side by side, into the cache the sections below then read
        threads, num_cpus = ray
        train_on_ray([job(*cell) for cell in planned_runs(s, recs)], threads=threads, num_cpus=num_cpus)
    runs = [run(*cell) for cell in tqdm(grid, desc="training runs", disable=not progress)]
    full = {r["fps"]: r for r in runs if r["scene"] == first and r["variant"] == "full"}
    fps = min(s.fps)
    full.setdefault(fps, run(first, fps, "full"))
    rec = recs[first][fps][0]
    model = load_run_model(full[fps], cache / "runs")
    knobs, context = render_sweep(model, rec, scales=s.render_scales, repeats=s.render_repeats,
                                  progress=progress)
    context |= {"scene": first, "fps": fps}
    sparse = {f: run(first, f, "full") for f in tqdm(s.sparse_fps, desc="sparse anchors",
                                                      disable=not progress)}
    stability = sparse_anchor_rows(sparse, {f: load_run_model(r, cache / "runs") for f, r in sparse.items()},
                                   {f: recs[first][f][0] for f in sparse}, full)
    stability += event_window_rows(model, rec)
    stability += pose_rows(model, rec)
    stability += precision_rows(list(s.scenes[: s.precision_scenes]), s.size)
    span_us = model.meta.t_end_us - model.meta.t_start_us
    resolution = {"recording_s": span_us / 1e6, "recording_us": span_us * 2.0**-24,
                  "day_ms": DAY_US * 2.0**-24 / 1000}
    lean, lean_context = collect_lean(s, recs, run, cache, fps, progress=progress)
    base_fps = max(set(s.fps) | set(s.sparse_fps))  # the rate scene_recordings built the first scene at
    long, prefix_diff = long_recording(first, fps, base_fps, rec, s, cache / "recordings", progress=progress)
    online, predictions, online_context = online_rows(long, cache / "runs" / full[fps]["checkpoint"], rec)
    online_context |= {"label": f"{first} {fps:g} fps", "prefix_diff": prefix_diff}
    return {"runs": runs, "baselines": baseline_rows(recs, runs), "knobs": knobs, "context": context,
            "stability": stability, "time_resolution": resolution, "lean": lean, "lean_context": lean_context,
            "online": online, "online_predictions": predictions, "online_context": online_context}


def planned_runs(s: ReportSettings, recs: dict) -> list[tuple]:
    """Every training run the report makes, as ``(scene, fps, variant[, (recording, cache key)])``: the
    grid, the first scene's full run at the lowest rate (the render sweep, the online section), its sparse
    rates, each scene's full run at that rate and the first's without events (the lean section) and its
    grey variant. ``--ray`` trains them all side by side first; the sections then find them cached."""
    first, fps = s.scenes[0], min(s.fps)
    cells = [(scene, f, v) for scene in s.scenes for f in s.fps for v in s.variants]
    cells += [(first, fps, "full"), *((first, f, "full") for f in s.sparse_fps)]
    cells += [(scene, fps, "full") for scene in s.scenes]
    if "no_events" in s.variants:
        cells.append((first, fps, "no_events"))
    rec, key = recs[first][fps]
    cells.append((first, fps, "full", (grey_recording(rec), f"{key}_grey")))
    unique = {}
    for cell in cells:  # first mention wins; a source is told apart by its cache key
        unique.setdefault((*cell[:3], cell[3][1] if len(cell) > 3 else None), cell)
    return list(unique.values())


def collect_lean(s: ReportSettings, recs: dict, run, cache: Path, fps: float, *,
                 progress: bool) -> tuple[list[dict], dict]:
    """What each scene's full run leaves out (report_lean.py), with the first scene's run without events,
    its weights frozen at a looser stated threshold, and a grey variant of it (one more training run)."""
    first, runs = s.scenes[0], cache / "runs"
    entries = [(f"{scene} {fps:g} fps", runs / run(scene, fps, "full")["checkpoint"],
                training_data(recs[scene][fps][0])) for scene in s.scenes]
    label, full_path, data = entries[0]
    context = {"full_label": label, "threads": torch.get_num_threads(), "repeats": s.render_repeats}
    if "no_events" in s.variants:
        context["no_events_label"] = f"{label} without events"
        without = runs / run(first, fps, "no_events")["checkpoint"]
        entries.append((context["no_events_label"], without, data))
        context["event_branch"] = event_branch_ms(full_path, without, data, repeats=s.render_repeats)
    context["refrozen_label"] = f"{label} frozen at the median motion"
    median = cache / "lean" / f"{full_path.stem}_median.ckpt"
    if not median.exists():
        median.parent.mkdir(parents=True, exist_ok=True)
        refrozen(full_path, median_threshold(full_path), median)
    entries.append((context["refrozen_label"], median, data))
    context["grey_label"] = f"{label} grey"
    rec, key = recs[first][fps]
    grey = grey_recording(rec)  # a DAVIS346's APS frames: one channel
    path = runs / run(first, fps, "full", source=(grey, f"{key}_grey"))["checkpoint"]
    entries.append((context["grey_label"], path, training_data(grey)))
    rows = lean_rows(entries, repeats=s.render_repeats, threads=torch.get_num_threads(), progress=progress)
    return rows, context


def write_outputs(out: Path, s: ReportSettings, r: dict, *, command: str, minutes: float,
                  threads: int) -> str:
    """CSV files, plots, ``summary.md`` and ``report.json``; returns the summary's text."""
    runs = r["runs"]
    ident = ("scene", "fps", "variant")
    curves = [{k: run[k] for k in ident} | c for run in runs for c in run["curve"]]
    # ssim_3dgs: absent from runs cached before it was recorded; every row gets the column all the same.
    frames = [{k: run[k] for k in ident} | {"ms_since_anchor": (f["t_us"] - f["anchor_us"]) / 1000} | f
              | {"ssim_3dgs": f.get("ssim_3dgs")} for run in runs for f in run["per_frame"]]
    columns = (*ident, "psnr", "ssim", "frames", "iterations", "train_seconds", "gaussians", "control_points",
               "nonfinite_steps")
    table = [{k: run[k] for k in columns} | {"ssim_3dgs": run.get("ssim_3dgs")} for run in runs]
    write_csv(out / "ablation.csv", table)
    write_csv(out / "baselines.csv", r["baselines"])
    write_csv(out / "training_curves.csv", curves)
    write_csv(out / "held_out_frames.csv", frames)
    write_csv(out / "render_knobs.csv", r["knobs"])
    write_csv(out / "stability.csv", r["stability"])
    write_csv(out / "lean.csv", r["lean"])
    write_csv(out / "online_drift.csv", r["online"])
    ablation_bars(table, out / "ablation.png")
    if r["online"]:
        c = r["online_context"]
        online_drift(r["online"], r["online_predictions"], out / "online_drift.png",
                     f"{c['steps']} steps of {c['lr']:g} at {c['scale']:g}x size, "
                     f"colours at {c['colour_lr']:g}")
    error_vs_time(runs, out / "error_vs_time.png", threads)
    render_knobs(r["knobs"], out / "render_knobs.png")
    machine = (f"{os.cpu_count()} CPUs ({threads} thread(s) used, load average {os.getloadavg()[0]:.1f} at "
               f"the end), torch {torch.__version__}")
    text = summary(settings=s, command=command, machine=machine, minutes=minutes, runs=runs,
                   baselines=r["baselines"], knobs=r["knobs"],
                   knob_context=r["context"], stability=r["stability"], tests=TEST_CASES,
                   time_resolution=r["time_resolution"], lean=lean_section(r["lean"], r["lean_context"]),
                   online=online_section(r["online"], r["online_predictions"], r["online_context"]))
    with atomic_output(out / "summary.md") as tmp:
        tmp.write_text(text)
    payload = {"settings": s.__dict__, "command": command, "minutes": minutes, "ablation": table,
               "baselines": r["baselines"],
               "curves": curves, "render_knobs": r["knobs"], "render_context": r["context"],
               "stability": r["stability"], "time_resolution": r["time_resolution"], "lean": r["lean"],
               "lean_context": r["lean_context"], "online": r["online"],
               "online_predictions": r["online_predictions"], "online_context": r["online_context"],
               "run": run_info() | {"command": command}}
    with atomic_output(out / "report.json") as tmp:
        tmp.write_text(json.dumps(payload, indent=1, default=str))
    return text


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    s = settings_from(args)
    if args.threads < 1:
        raise SystemExit(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    started = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    results = collect(s, args.out / "cache", device=args.device, progress=not args.quiet,
                      ray=(args.threads, args.ray_cpus) if args.ray else None)
    command = " ".join(["python -m bench.report", *(sys.argv[1:] if argv is None else argv)])
    minutes = (time.perf_counter() - started) / 60
    text = write_outputs(args.out, s, results, command=command, minutes=minutes, threads=args.threads)
    print(text.split("## 2.")[0])
    print(f"wrote {args.out / 'summary.md'} ({minutes:.1f} min)")
    return 0 if all(row["ok"] for row in results["stability"]) else 1


if __name__ == "__main__":
    sys.exit(main())
