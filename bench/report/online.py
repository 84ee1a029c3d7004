"""The report's online section: the full model served past the span it was trained on.

The same scene is built ``SPANS`` times longer with the same settings (the simulation is deterministic,
so its first stretch is the training recording: checked, and said when it is not), replayed past the
checkpoint with online anchors (``bench.online.drift``: each new frame predicted by the event
transition, then corrected as the server does), and every held-out frame past the span scored beside
the causal baselines. The drift plot is ``online_drift.png``; the rows ``online_drift.csv``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.online import BAND_S, bands
from bench.report.data import build_config, cached_build, fewer_anchors
from bench.report.settings import ReportSettings
from edmcgs.sensor.files.recording import Recording

SPANS = 4
"""The long recording spans this many times the training recording."""
COLUMNS = (("live", "live render (online anchors, corrected, projected onto the events since the frame)"),
           ("live_model", "the same before the projection (the model alone)"),
           ("no_corr", "the live render never corrected"),
           ("no_events", "the same fits without events moving the anchors (the event branch's ablation)"),
           ("hold_last", "hold the last anchor frame (no model)"),
           ("hold_projected", "that frame projected onto the events (no model)"),
           ("integrate", "events integrated onto the last anchor (no model)"))


def long_recording(scene: str, fps: float, base_fps: float, short: Recording, s: ReportSettings,
                   cache: Path, *, progress: bool) -> tuple[Recording, float]:
    """The scene ``SPANS`` times as long, at ``fps`` derived from ``base_fps`` as ``scene_recordings``
    derives it; and how far its first stretch is from ``short`` (largest anchor pixel difference, 0-255;
    inf when the anchor times differ)."""
    span_s = (short.anchors.t_us[-1] - short.anchors.t_us[0]) / 1e6
    cfg = replace(build_config(scene, base_fps, s), duration_s=SPANS * (s.duration_s or span_s))
    base, _ = cached_build(cfg, cache, progress=progress)
    rec = fewer_anchors(base, round(base_fps / fps))
    n = len(short.anchors.t_us)
    if len(rec.anchors.t_us) < n or not np.array_equal(rec.anchors.t_us[:n], short.anchors.t_us):
        return rec, math.inf
    diff = np.abs(rec.anchors.images[:n].astype(np.int16) - short.anchors.images.astype(np.int16)).max()
    return rec, float(diff)


def online_rows(rec: Recording, checkpoint: Path, training: Recording) -> tuple[list[dict], list[dict], dict]:
    """(drift rows, prediction rows, context) with the server's defaults, the checkpoint given its online
    transition first as ``edmcgs distill`` would from ``training`` (its recording; cached beside it as
    NAME.online.ckpt), unless its event branch cannot have one."""
    from bench.online import drift
    from edmcgs.errors import InvalidInputError
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.online.distill import distill, save_with
    from edmcgs.pipeline import training_data
    from edmcgs.server.settings import Settings

    fit = {k: Settings.model_fields[f"online_fit_{k}"].default for k in ("steps", "scale", "lr")}
    fit["colour_lr"] = Settings.model_fields["online_colour_lr"].default
    fit["distilled"] = "no event branch"
    served = checkpoint.with_name(checkpoint.stem + ".online.ckpt")
    if not served.exists():
        model = load_checkpoint(checkpoint)
        model.requires_grad_(False)
        try:
            save_with(model, distill(model, training_data(training).event_map).transition, served)
        except InvalidInputError as exc:
            fit["distilled"] = str(exc)
    if served.exists():
        checkpoint, fit["distilled"] = served, "yes"
    transition = Settings.model_fields["online_transition"].default
    rows, extra = drift(rec, checkpoint, fit["steps"], fit["scale"], fit["lr"], transition=transition,
                        colour_lr=fit["colour_lr"])
    chosen = [p["transition"] for p in extra["pred"]]
    fit["transition"] = ", ".join(f"{name} at {chosen.count(name)}" for name in dict.fromkeys(chosen))
    return rows, extra["pred"], fit


def section(rows: list[dict], predictions: list[dict], context: dict) -> list[str]:
    """The summary's Markdown lines."""
    head = ["## 6. Online anchors past the span", ""]
    if not rows:
        return [*head, "No held-out frame past the span: not measured.", ""]
    live = np.array([r["live"] for r in rows])
    out = [*head,
           f"The full model ({context['label']}) served over a recording {SPANS} times as long, built with "
           "the same settings (its first stretch is the training recording"
           + ("" if context["prefix_diff"] == 0 else
              f"; it differs from it by up to {context['prefix_diff']:g} of 255 in an anchor pixel") + "). "
           "Past the span every new anchor frame is predicted by the event transition, then corrected with "
           f"the server's default fit ({context['steps']} Adam steps of {context['lr']:g} at "
           f"{context['scale']:g}x size, colour offsets at {context['colour_lr']:g}) before "
           f"the next; the transition is chosen by the frames (distilled online transition: "
           f"{context.get('distilled', 'no')}; chosen: {context.get('transition') or 'none yet'}); "
           "each render of the event camera's view is projected onto the events since its anchor's "
           f"frame (model/online/bounds.py); {len(rows)} held-out frames past the span, mean PSNR (dB):", "",
           "| | mean PSNR | first half | second half | frames >= hold-last |", "|---|---|---|---|---|"]
    half = len(rows) // 2
    hold = np.array([r["hold_last"] for r in rows])
    for key, label in COLUMNS:
        v = np.array([r[key] for r in rows])
        out.append(f"| {label} | {v.mean():.2f} | {v[:half].mean() if half else v.mean():.2f} | "
                   f"{v[half:].mean():.2f} | {int((v >= hold - 1e-9).sum())} / {len(v)} |")
    pred = np.mean([p["pred_psnr"] for p in predictions]) if predictions else float("nan")
    causal = ("hold_last", "hold_projected", "integrate")
    best_baseline = max(np.mean([r[k] for r in rows]) for k in causal)
    verdict = "beats" if live.mean() > best_baseline else "does not beat"
    summary = bands(rows)
    worst = min(summary, key=lambda b: b["live"] - b["hold_last"])
    pooled = min(b["live_pooled"] - b["hold_last_pooled"] for b in summary)
    out += ["", f"Each new anchor frame against its prediction before correction: {pred:.2f} dB. The live "
            f"render {verdict} the three causal baselines on average; its worst frame is "
            f"{float((live - hold).min()):+.2f} dB against hold-last, its worst {BAND_S:g} s band since "
            f"training ended ({worst['from_s']:g}-{worst['to_s']:g} s) "
            f"{worst['live'] - worst['hold_last']:+.2f} dB (mean of dB; by the band's pooled PSNR, its "
            f"worst is {pooled:+.2f} dB).", "",
            "![online drift](online_drift.png)", ""]
    return out
