"""The report's figures (matplotlib's object API on the Agg canvas: no global backend state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from bench.figures import save
from bench.report.paper import PAPER_SYNTHETIC
from bench.report.settings import VARIANTS

COLORS = {"full": "#1b6ca8", "no_events": "#d1495b", "no_markov": "#edae49", "no_local_sampling": "#66a182",
          "no_tli": "#8e6c8a"}


def error_vs_time(runs: list[dict], path: Path, threads: int) -> None:
    """Held-out PSNR and SSIM against training time, one row per (scene, rate), one line per variant."""
    groups = sorted({(r["scene"], r["fps"]) for r in runs})
    fig = Figure(figsize=(11, 3.0 * len(groups) + 0.8), layout="constrained")
    axes = fig.subplots(len(groups), 2, squeeze=False)
    for row, (scene, fps) in enumerate(groups):
        for r in (r for r in runs if (r["scene"], r["fps"]) == (scene, fps)):
            x = [c["seconds"] for c in r["curve"]]
            for col, metric in enumerate(("psnr", "ssim")):
                axes[row, col].plot(x, [c[metric] for c in r["curve"]], marker="o", ms=3,
                                    color=COLORS.get(r["variant"]), label=VARIANTS[r["variant"]][1])
        for col, name in enumerate(("PSNR (dB)", "SSIM")):
            ax = axes[row, col]
            ax.set_title(f"{scene}, {fps:g} fps anchors: held-out {name.split()[0]}")
            ax.set_ylabel(name)
            ax.set_xlabel(f"training time (s on {threads} CPU thread(s), evaluation excluded)")
            ax.grid(alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncols=len(labels))
    save(fig, path)


def render_knobs(rows: list[dict], path: Path) -> None:
    """Per knob: error against the float64 reference (top) and PSNR against ground truth (bottom) over
    the time each setting takes."""
    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    fig = Figure(figsize=(3.4 * len(knobs), 6.4), layout="constrained")
    axes = fig.subplots(2, len(knobs), squeeze=False)
    for col, knob in enumerate(knobs):
        sel = [r for r in rows if r["knob"] == knob]
        per_frame = knob == "control points"  # the deformation is what this knob changes
        x = np.array([r["ms_frame"] if per_frame else r["ms_render"] for r in sel])
        err = np.maximum([r["rmse_ref"] for r in sel], 1e-8)
        gt = np.array([r["psnr_gt"] for r in sel])
        panels = ((err, "RMSE vs float64 reference"), (gt, "PSNR vs ground truth (dB)"))
        for row, (y, label) in enumerate(panels):
            ax = axes[row, col]
            ax.plot(x, y, ls=":", lw=0.8, color="#1b6ca8")  # in knob order
            ax.plot(x, y, ls="", marker="o", color="#1b6ca8")
            for n, (xi, yi, r) in enumerate(zip(x, y, sel, strict=True)):
                ax.annotate(_label(knob, r), (xi, yi), textcoords="offset points", fontsize=7,
                            xytext=(4, 4 if n % 2 else -10))  # alternate sides: equal points stay legible
            ax.set_ylabel(label)
            ax.set_xlabel("deform + render (ms per frame)" if per_frame else "render (ms per frame)")
            ax.set_xlim(left=0)  # times relative to zero: noise between close settings is not magnified
            ax.grid(alpha=0.3)
        axes[0, col].set_yscale("log")
        axes[0, col].set_title(f"{knob}{' (Gaussians kept)' if knob == 'opacity threshold' else ''}")
        lo, hi = float(np.min(gt)), float(np.max(gt))
        axes[1, col].ticklabel_format(axis="y", useOffset=False)
        axes[1, col].set_ylim(min(lo, (lo + hi) / 2 - 0.5) - 0.2, max(hi, (lo + hi) / 2 + 0.5) + 0.2)
    fig.suptitle("Fast path knobs: error against time per frame (one held-out frame of the trained full "
                 "model; median times; default alpha_min 1/255, t_min 1e-4)")
    save(fig, path)


def _label(knob: str, r: dict) -> str:
    if knob == "opacity threshold":
        return f"{r['value']:g} ({r['gaussians']})"
    if knob == "resolution":
        return f"{r['width']}x{r['height']}"
    if knob == "alpha_min" and abs(r["value"] - 1 / 255) < 1e-12:
        return "1/255"
    return f"{r['value']:g}"


def ablation_bars(table: list[dict], path: Path) -> None:
    """Mean held-out PSNR per variant and rate (this report) beside the paper's averages (their data)."""
    rates = sorted({r["fps"] for r in table})
    fig = Figure(figsize=(5.5 * len(rates), 4.2), layout="constrained")
    axes = fig.subplots(1, len(rates), squeeze=False)[0]
    for ax, fps in zip(axes, rates, strict=True):
        variants = [v for v in VARIANTS if any(r["variant"] == v and r["fps"] == fps for r in table)]
        ours = [float(np.mean([r["psnr"] for r in table if r["variant"] == v and r["fps"] == fps]))
                for v in variants]
        paper = [PAPER_SYNTHETIC.get(fps, {}).get(v, (np.nan,))[0] for v in variants]
        pos = np.arange(len(variants))
        colors = [COLORS[v] for v in variants]
        ax.bar(pos - 0.2, ours, 0.4, color=colors)
        ax.bar(pos + 0.2, paper, 0.4, color=colors, alpha=0.35, hatch="//")
        for p, o, q in zip(pos, ours, paper, strict=True):
            ax.annotate(f"{o:.2f}", (p - 0.2, o), ha="center", va="bottom", fontsize=8)
            ax.annotate("not reported" if np.isnan(q) else f"{q:.2f}", (p + 0.2, q if np.isfinite(q) else o),
                        ha="center", va="bottom", fontsize=7, rotation=0 if np.isfinite(q) else 90)
        ax.set_xticks(pos, [VARIANTS[v][1] for v in variants], rotation=20, ha="right")
        ax.set_xlim(-0.7, len(variants) - 0.3)
        ax.set_ylabel("held-out PSNR (dB)")
        finite = [v for v in ours + paper if np.isfinite(v)]
        ax.set_ylim(min(finite) - 3, max(finite) + 4)
        ax.set_title(f"Ablations at {fps:g} fps anchors (mean over scenes)")
        legend = [Patch(color="grey", label="this report (our synthetic data)"),
                  Patch(facecolor="grey", alpha=0.35, hatch="//", label="paper (their data, 30k it.)")]
        ax.legend(handles=legend, fontsize=8, loc="upper right")
        ax.grid(axis="y", alpha=0.3)
    save(fig, path)


