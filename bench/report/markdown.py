"""The report's Markdown summary (``summary.md``), written from the collected results."""

from __future__ import annotations

import numpy as np

from bench.report.paper import PAPER_SYNTHETIC, PAPER_TRAINING
from bench.report.settings import VARIANTS, ReportSettings
from edmcgs.model.eval.lpips import SKIPPED as LPIPS_SKIPPED

FILES = {
    "ablation.csv": "final held-out PSNR / SSIM of every run (scene, rate, variant), with training time",
    "baselines.csv": "hold the last anchor / blend the neighbouring anchors (no model) on the same frames",
    "training_curves.csv": "held-out PSNR / SSIM at the evaluation steps of every run, by training seconds",
    "held_out_frames.csv": "per held-out frame of every run: time since its anchor, events, PSNR, SSIM",
    "render_knobs.csv": "the fast path's knob sweep: times, error against the float64 reference and truth",
    "stability.csv": "the stability cases measured by the report (the fast ones are in tests/)",
    "lean.csv": "what each checkpoint leaves out; deform, render, size and error against its full twin",
    "online_drift.csv": "per held-out frame past the span: the live render, uncorrected, without events, "
                        "and the baselines",
    "ablation.png": "mean PSNR per variant and rate beside the paper's averages",
    "error_vs_time.png": "held-out PSNR / SSIM against training time, every variant",
    "render_knobs.png": "error against time per frame for each fast-path knob",
    "online_drift.png": "PSNR against time since training ended, online anchors beside the baselines",
    "report.json": "everything above in one file",
}


def _mean(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows])) if rows else float("nan")


def _ssim_3dgs(rows: list[dict]) -> str:
    """Mean SSIM in the 3DGS convention, the one the paper's numbers use ("—" for runs cached before it
    was recorded)."""
    values = [r.get("ssim_3dgs") for r in rows]
    return "—" if not values or None in values else f"{np.mean(values):.4f}"


def _paper_cell(fps: float, variant: str) -> str:
    p = PAPER_SYNTHETIC.get(fps, {}).get(variant)
    return "—" if p is None else f"{p[0]:.2f} / {p[1]:.4f} / {p[2]:.4f}"


def ablation_table(runs: list[dict], settings: ReportSettings, baselines: list[dict]) -> list[str]:
    rates = sorted({r["fps"] for r in runs})
    cols = [f"{f:g} fps PSNR | SSIM (3DGS) | Δ PSNR vs full | paper {f:g} fps PSNR / SSIM / LPIPS"
            for f in rates]
    lines = ["| variant | " + " | ".join(cols) + " |", "|---|" + "---:|---:|---:|---:|" * len(rates)]
    for v in settings.variants:
        cells = []
        for fps in rates:
            sel = [r for r in runs if r["variant"] == v and r["fps"] == fps]
            full = [r for r in runs if r["variant"] == "full" and r["fps"] == fps]
            delta = "" if v == "full" or not full else f"{_mean(sel, 'psnr') - _mean(full, 'psnr'):+.2f}"
            cells += [f"{_mean(sel, 'psnr'):.2f}", _ssim_3dgs(sel), delta, _paper_cell(fps, v)]
        lines.append(f"| {VARIANTS[v][1]} | " + " | ".join(cells) + " |")
    for name in dict.fromkeys(b["baseline"] for b in baselines):
        cells = []
        for fps in rates:
            sel = [b for b in baselines if b["baseline"] == name and b["fps"] == fps]
            full = [r for r in runs if r["variant"] == "full" and r["fps"] == fps]
            delta = f"{_mean(sel, 'psnr') - _mean(full, 'psnr'):+.2f}" if full and sel else ""
            cells += [f"{_mean(sel, 'psnr'):.2f}", _ssim_3dgs(sel), delta, "—"]
        lines.append(f"| {name} (no model) | " + " | ".join(cells) + " |")
    return lines


def baseline_verdict(runs: list[dict], baselines: list[dict]) -> str:
    """One sentence per rate: which baselines the full model does not beat (mean PSNR), or that it beats
    them all."""
    parts = []
    for fps in sorted({r["fps"] for r in runs}):
        full = _mean([r for r in runs if r["variant"] == "full" and r["fps"] == fps], "psnr")
        names = dict.fromkeys(b["baseline"] for b in baselines if b["fps"] == fps)
        losing = [(n, _mean([b for b in baselines if b["baseline"] == n and b["fps"] == fps], "psnr"))
                  for n in names]
        losing = [(n, v) for n, v in losing if v >= full]
        if losing:
            parts.append(f"at {fps:g} fps the full model ({full:.2f} dB) does **not** beat "
                         + " nor ".join(f"{n} ({v:.2f} dB)" for n, v in losing))
        elif names:
            parts.append(f"at {fps:g} fps the full model ({full:.2f} dB) beats every baseline")
    return ("Against the baselines: " + "; ".join(parts) + ".") if parts else ""


def per_run_table(runs: list[dict]) -> list[str]:
    lines = ["| scene | fps | variant | PSNR (dB) | SSIM | SSIM (3DGS) | LPIPS | frames | train s "
             "| s / step | Gaussians | non-finite steps |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in runs:
        per_step = r["train_seconds"] / r["iterations"]
        lpips = "—" if r.get("lpips") is None else f"{r['lpips']:.4f}"
        lines.append(f"| {r['scene']} | {r['fps']:g} | {VARIANTS[r['variant']][1]} | {r['psnr']:.2f} | "
                     f"{r['ssim']:.4f} | {_ssim_3dgs([r])} | {lpips} | {r['frames']} | "
                     f"{r['train_seconds']:.0f} | "
                     f"{per_step:.3f} | {r['gaussians']} | {r['nonfinite_steps']} |")
    return lines


def curve_table(runs: list[dict]) -> list[str]:
    lines = ["| scene | fps | variant | PSNR at step 0 → mid → end (dB) | best PSNR (step) "
             "| SSIM at step 0 → end | train s |", "|---|---:|---|---|---|---|---:|"]
    for r in runs:
        c = r["curve"]
        mid, best = c[len(c) // 2], max(c, key=lambda p: p["psnr"])
        lines.append(f"| {r['scene']} | {r['fps']:g} | {VARIANTS[r['variant']][1]} | {c[0]['psnr']:.2f} → "
                     f"{mid['psnr']:.2f} (step {mid['step']}) → {c[-1]['psnr']:.2f} | {best['psnr']:.2f} "
                     f"({best['step']}) | {c[0]['ssim']:.4f} → {c[-1]['ssim']:.4f} | "
                     f"{c[-1]['seconds']:.0f} |")
    return lines


def knob_table(rows: list[dict]) -> list[str]:
    lines = ["| knob | value | Gaussians | control points | size | deform ms | render ms "
             "| RMSE vs float64 ref | max abs vs ref | PSNR vs truth (dB) | SSIM vs truth |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['knob']} | {r['value']:g} | {r['gaussians']} | {r['control_points']} | "
                     f"{r['width']}x{r['height']} | {r['ms_deform']:.1f} | {r['ms_render']:.2f} | "
                     f"{r['rmse_ref']:.1e} | {r['max_abs_ref']:.1e} | {r['psnr_gt']:.2f} | "
                     f"{r['ssim_gt']:.4f} |")
    return lines


def stability_table(rows: list[dict], tests: list[tuple[str, str, str]]) -> list[str]:
    lines = ["| case | what is checked | result | held | where |", "|---|---|---|---|---|"]
    for r in rows:
        held = "yes" if r["ok"] else "**no**"
        lines.append(f"| {r['case']} | {r['check']} | {r['result']} | {held} | report |")
    for case, check, where in tests:
        lines.append(f"| {case} | {check} | asserted by the test suite | pytest | `{where}` |")
    return lines


def summary(*, settings: ReportSettings, command: str, machine: str, minutes: float, runs: list[dict],
            baselines: list[dict], knobs: list[dict], knob_context: dict, stability: list[dict],
            tests: list[tuple[str, str, str]], time_resolution: dict, lean: list[str],
            online: list[str]) -> str:
    s, c, tr = settings, knob_context, time_resolution
    if s.name == "small":
        scale = ("a smoke-scale run: far from converged and not comparable with the paper's numbers "
                 "(`--full` runs the paper's grid)")
    else:
        scale = "the paper's grid at the demo preset's length"
    length = "the scene's length" if s.duration_s is None else f"{s.duration_s:g} s"
    train_scale = "its train scale" if s.train_scale is None else f"train scale {s.train_scale:g}"
    cached = sum(r["cached"] for r in runs)
    reused = ""
    if cached:
        reused = f" ({cached} of {len(runs)} training runs reused from `cache/`, timed when they ran)"
    out = [
        f"# edmcgs report ({s.name})", "",
        f"Made by `{command}` in {minutes:.1f} min{reused} on {machine}. Timings are wall-clock medians on a "
        "shared machine: noisy; compare them within this report only.", "",
        f"Scenes {', '.join(s.scenes)} ({s.size}, {length}), anchors at {', '.join(f'{f:g}' for f in s.fps)} "
        f"fps, preset `{s.preset}` ({train_scale}), {s.iterations} training steps per run: {scale}.", "",
        "## 1. Ablations", "",
        "Held-out PSNR / SSIM averaged over the scenes (every ground-truth frame between the anchors), "
        "the trivial baselines on the same frames (a method that does not beat them has not worked), and "
        "beside the paper's reported averages for context only: theirs are on their own data "
        f"({PAPER_TRAINING}); the paper reports only the full model and w/o Markov at 10 fps. SSIM here is "
        "in the 3DGS papers' convention (zero-padded windows over the full image), as the paper's; the "
        "per-run table below has both (SSIM: windows inside the image only, as `edmcgs eval` prints first).",
        "",
        *ablation_table(runs, s, baselines), "", baseline_verdict(runs, baselines), "",
        "![ablations](ablation.png)", "", *per_run_table(runs), "",
        "LPIPS (VGG): scored on the weights found on disk." if any(r.get("lpips") is not None for r in runs)
        else f"{LPIPS_SKIPPED}.", "",
        "## 2. Error against training time", "",
        "Every run is evaluated on all its held-out frames at fixed steps; the clock counts `train_step` "
        "only (evaluation excluded), so every variant is on the same time axis.", "",
        "![error against training time](error_vs_time.png)", "", *curve_table(runs), "",
        "## 3. Render error against time per frame", "",
        f"One held-out frame of the trained full model ({c['scene']}, {c['fps']:g} fps): frame {c['frame']}, "
        f"{c['ms_since_anchor']:.0f} ms after its anchor, {c['events']} events in its window, "
        f"{c['gaussians']} Gaussians, {c['control_points']} control points, {c['width']}x{c['height']}, "
        f"{c['threads']} thread(s). The float64 reference is `model/render/reference.py` (every pixel "
        "against every Gaussian) at the same resolution with all Gaussians, all control points and the "
        "default knobs (alpha_min 1/255, t_min 1e-4); the truth is the scene's own Gaussians rendered at "
        f"that resolution (at full size it matches the stored held-out frame to "
        f"{c['gt_vs_held_out_psnr']:.1f} dB: uint8 rounding).", "",
        "![render knobs](render_knobs.png)", "", *knob_table(knobs), "",
        "## 4. Stability on stiff and extreme cases", "",
        "Measured here on the trained models and the benchmark scenes (slow), then the fast cases that the "
        "test suite asserts (`.venv/bin/python -m pytest tests/stability`).", "",
        *stability_table(stability, tests), "",
        "Time: every window, anchor and trajectory lookup uses int64 microseconds; the model normalises time "
        "to [0, 1] in float64 and its networks take it as float32, whose spacing below 1 is 2^-24 of the "
        f"span: {tr['recording_us']:.3g} µs over this recording's {tr['recording_s']:g} s, "
        f"{tr['day_ms']:.1f} ms over a 24-hour recording (the networks cannot tell apart times closer than "
        "that; the event windows can).", "",
        *lean,
        *online,
        "## Files", "",
        *[f"- `{name}`: {what}" for name, what in FILES.items()],
        "- `cache/`: the built recordings and trained checkpoints (delete it to start over)", "",
    ]
    return "\n".join(out)
