"""Online anchors past the checkpoint's span: drift against time since training ended, and what a
correction costs.

    .venv/bin/python -m bench.online --recording LONG.h5 --checkpoint SHORT.ckpt [--json PATH] [--csv PATH]
    .venv/bin/python -m bench.online ... --timing-only   (the CPU figures alone)

With a recording longer than the checkpoint's span (its anchors at the checkpoint's anchor rate past the
span, its ``held_out`` frames as ground truth), the recording is fed as a replay would (events, then
each anchor frame past the span), each online anchor predicted by the event transition and, for the
"corrected" chain, fitted to its frame before the next (a fit that keeps up); then every held-out frame
past the span is scored (PSNR) for

    live       the service's render of the event camera's view: newest corrected anchor before t + the
               events since it, projected onto the bounds the anchor's frame and those events put on
               each pixel (``project``: the server's ``online_project``; model/online/bounds.py)
    live_model the same render before that projection: the model alone
    no_corr    the live chain, never corrected (the model's transition alone), projected as ``live``
    no_events  the ablation of the events past the span: the same fits with no transition (each
               anchor predicted as the one before it; a render holds its anchor's state), projected as
               ``live`` (the events then bound the render only)
    hold_last  the newest anchor frame itself (no model)
    hold_projected  that frame projected as ``live`` is: the projection with no model
    integrate  the events since it integrated onto that frame (no model; ``model/eval/baselines.py``)
    blend      the anchor frames either side blended linearly in time (no model, not causal: None past
               the last anchor)

each also on the moving pixels alone (``NAME_moving``: where the frame differs from the median of the
span's anchor frames by more than ``MOVING``, as bench.traffic scores them, pooled over the frames in
the results; None where none moves);

by 1 s band of time since training ended, each render's mean PSNR, and for the live render and
hold-last the band's pooled PSNR (of its mean squared error) with the frames the live render scores at
least as well as hold-last: a mean of dB lets the few frames where the scene is back where its anchor
left it (hold-last near exact) outweigh the rest;

and each new anchor frame against its prediction before the correction (``pred``; ``transition``: what
moved the anchors past the span after its fit, server/online.py) and against the
corrected anchor itself (``corrected_psnr``: the floor of a live render's error right after that frame,
where holding the frame itself is exact). Timing: one
correction per anchor of the checkpoint's model at 173x130 and 346x260 (intrinsics scaled), anchors per
second sustained with predict + correct back to back, one torch thread.
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
import torch

from bench.results import table, write_json

TARGETS = {"anchors_per_s_173x130": (">=", 5.0),
           # a live render no worse than hold-last at any time since training ended (per band)
           "live_minus_hold_last_worst_band_db": (">=", 0.0)}
BAND_S = 1.0
"""Width of the time bands the drift is summarised in (``bands``)."""
MOVING = 0.06
"""A pixel is moving in a frame where it differs from the span's anchors' median by more than this."""
RENDERS = ("live", "live_model", "no_corr", "no_events", "hold_last", "hold_projected", "integrate")
"""What every held-out frame is scored for (``blend`` beside them where there is a next anchor)."""


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 99.0 if mse == 0 else 10 * np.log10(1.0 / mse)


def drift(recording, checkpoint: Path, steps: int, scale: float, lr: float, finetune_steps: int = 0,
          finetune_lr: float = 1e-4, spawn: int = 0, transition: str = "select",
          colour_lr: float = 0.0, project: bool = True) -> tuple[list[dict], dict]:
    """recording: a path or a ``Recording``; finetune_*, spawn, transition, colour_lr, project: the
    server's ``online_finetune_*``, ``online_spawn``, ``online_transition``, ``online_colour_lr`` and
    ``online_project``; see the module docstring."""
    from edmcgs.geometry import Trajectory
    from edmcgs.model import online as model_online
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.eval.baselines import DEFAULT_CONTRAST
    from edmcgs.model.online.bounds import integrate
    from edmcgs.model.online.bounds import project as project_events
    from edmcgs.sensor.buffer.ring import EventRingBuffer
    from edmcgs.sensor.event_map import accumulate
    from edmcgs.sensor.files.recording import Recording, read_recording
    from edmcgs.sensor.frames import Frames
    from edmcgs.server.engine import Engine
    from edmcgs.server.live.anchors import OnlineAnchors
    from edmcgs.server.live.clock import Timeline
    from edmcgs.server.live.config import OnlineConfig
    from edmcgs.server.live.timebase import Timebase

    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    contrast = DEFAULT_CONTRAST if rec.contrast_threshold is None else rec.contrast_threshold
    model = load_checkpoint(checkpoint)
    meta = model.meta
    end = int(meta.t_end_us)
    traj = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w) if rec.trajectory_t_us is not None else None

    def pose(t):
        return traj.at(int(t)) if traj is not None else meta.trajectory.at(int(t))

    start = rec.t_range_us[0]
    chains = {}
    pred_rows = []
    for name, fit, moves in (("live", True, transition), ("no_corr", False, transition),
                             ("no_events", True, "none")):
        ring = EventRingBuffer(len(rec.events) + 1)
        ring.push(rec.events, complete_until_us=rec.t_range_us[1] + 1)
        online = OnlineAnchors(model, ring, OnlineConfig(
            capacity=10**6, fit=False, fit_steps=steps, fit_scale=scale, fit_lr=lr,
            finetune_steps=finetune_steps, finetune_lr=finetune_lr, spawn=spawn, colour_lr=colour_lr,
            transition=moves, project=project), pose=pose)
        engine = Engine(Timebase(model, online), ring, cache_size=4)
        engine.timeline = Timeline(start, start)
        anchors = rec.anchors
        # the frames from the checkpoint's last anchor on, as a replay delivers them (that one: what
        # renders past the span are projected onto until the first online anchor)
        for i in np.nonzero(anchors.t_us >= int(meta.anchors_us[-1]))[0]:
            t = int(anchors.t_us[i])
            frame = Frames(anchors.t_us[i:i + 1], anchors.images[i:i + 1],
                           None if anchors.poses is None else anchors.poses[i:i + 1])
            online.on_frames(frame, engine.timeline.scene_of)
            if t <= end:
                continue
            a = online.anchors()[-1]
            if fit and name != "live":
                online._fit(a, anchors.images[i])
            elif fit:  # the live chain's fits are also scored
                state = model_online.with_spawned(model_online.state_of(model, a.motion, a.colors), a.spawned)
                img = model.render(state, pose(t), meta.intrinsics)
                pred = _psnr(img, anchors.images[i] / 255.0)
                t0 = time.perf_counter()
                online._fit(a, anchors.images[i])
                fit_s = time.perf_counter() - t0
                fitted = online.anchors()[-1]  # the corrected anchor, against the frame it was fitted to
                state = model_online.with_spawned(model_online.state_of(model, fitted.motion, fitted.colors),
                                                  fitted.spawned)
                corrected = _psnr(model.render(state, pose(t), meta.intrinsics), anchors.images[i] / 255.0)
                pred_rows.append({"t_us": t, "since_end_s": (t - end) / 1e6, "pred_psnr": pred,
                                  "corrected_psnr": corrected, "fit_s": fit_s,
                                  "transition": online.transitions.kind,
                                  "loss_before": online.last_loss[0], "loss_after": online.last_loss[1]})
        chains[name] = engine
    held = rec.held_out
    rows = []
    anchor_t = rec.anchors.t_us
    # moving pixels (as bench.traffic scores them): where a frame differs from the median of the
    # checkpoint's span's anchor frames
    still = np.median(rec.anchors.images[anchor_t <= end], axis=0) / 255.0
    for j in np.nonzero(held.t_us > end)[0]:
        t = int(held.t_us[j])
        target = held.images[j] / 255.0
        c2w = held.poses[j] if held.poses is not None else pose(t)
        row = {"t_us": t, "since_end_s": (t - end) / 1e6}
        images = {}
        size = (meta.intrinsics.width, meta.intrinsics.height)
        for name, engine in chains.items():  # the held-out frame's pose is the event camera's
            images[name] = engine.render(t, c2w, *size, camera_view=True).pixels / 255.0
        images["live_model"] = chains["live"].render(t, c2w, *size, camera_view=False).pixels / 255.0
        k = int(np.searchsorted(anchor_t, t, side="right")) - 1
        frame = rec.anchors.images[k] / 255.0
        images["hold_last"] = frame
        # blend of the anchors either side (not causal: it needs the next frame), where there is one
        if k + 1 < len(anchor_t):
            w = (t - int(anchor_t[k])) / float(anchor_t[k + 1] - anchor_t[k])
            images["blend"] = (1 - w) * frame + w * rec.anchors.images[k + 1] / 255.0
        events = accumulate(rec.events.time_slice(int(anchor_t[k]), t), rec.width, rec.height)
        images["integrate"] = integrate(frame, events, contrast)
        images["hold_projected"] = frame if not project else project_events(
            frame, frame, events, model.config.contrast_threshold, eps=model.config.log_eps)
        moving = np.abs(target - still).max(-1) > MOVING
        row["moving_px"] = int(moving.sum())
        for name in (*RENDERS, "blend"):
            img = images.get(name)
            row[name] = None if img is None else _psnr(img, target)
            row[f"{name}_moving"] = None if img is None or not moving.any() else \
                _psnr(img[moving], target[moving])
        rows.append(row)
    return rows, {"pred": pred_rows}


def pooled(scored: list[tuple[float, int]]) -> float | None:
    """PSNR of the mean squared error of (PSNR, pixels) pairs: every pixel weighs the same, so a few
    near-exact frames do not outweigh the rest as they do in a mean of dB. None for no pair."""
    if not scored:
        return None
    mse = sum(10 ** (-p / 10) * n for p, n in scored) / sum(n for _, n in scored)
    return float(-10 * np.log10(mse))


def bands(rows: list[dict], width_s: float = BAND_S) -> list[dict]:
    """Mean PSNR of each render in successive ``width_s`` bands of time since training ended (the drift
    curve, smoothed over the anchor cycle); beside it, for the live render and the two anchor baselines,
    the band's pooled PSNR (``pooled``), and how many of its frames the live render scores at least as
    well as hold-last. The blend of the anchors either side is over the frames that have one (None if
    none: past the last anchor)."""
    out = []
    index = np.array([int(r["since_end_s"] // width_s) for r in rows])
    for k in np.unique(index):
        sel = [r for r, i in zip(rows, index, strict=True) if i == k]
        band = {"from_s": float(k * width_s), "to_s": float((k + 1) * width_s), "frames": len(sel)}
        for name in RENDERS:
            band[name] = float(np.mean([r[name] for r in sel]))
        blend = [r["blend"] for r in sel if r.get("blend") is not None]
        band["blend"] = float(np.mean(blend)) if blend else None
        for name in ("live", "hold_last", "blend"):
            band[f"{name}_pooled"] = pooled([(r[name], 1) for r in sel if r.get(name) is not None])
        band["live_wins"] = int(sum(r["live"] >= r["hold_last"] for r in sel))
        out.append(band)
    return out


def timing(checkpoint: Path, recording: Path, width: int, height: int, steps: int, scale: float, lr: float,
           colour_lr: float = 0.0, n: int = 6) -> dict:
    """Median predict and correct time per anchor of ``checkpoint``'s model, its anchors rendered and
    compared at width x height (intrinsics scaled, the frame resized to match)."""
    from edmcgs.model import online as model_online
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.sensor.event_map import accumulate
    from edmcgs.sensor.files.recording import read_recording

    rec, model = read_recording(recording), load_checkpoint(checkpoint)
    model.requires_grad_(False)
    meta = model.meta
    intr = meta.intrinsics.scaled(width, height)
    motion, colors = model_online.checkpoint_motion(model, int(meta.t_end_us)), None
    poses = rec.anchors.poses if rec.anchors.poses is not None else None
    preds, fits = [], []
    for k in range(n + 1):
        i = 1 + k % (len(rec.anchors) - 1)
        t = int(rec.anchors.t_us[i])
        emap = accumulate(rec.events.time_slice(int(rec.anchors.t_us[i - 1]), t), meta.event_width,
                          meta.event_height)
        c2w = poses[i] if poses is not None else meta.trajectory.at(t)
        image = torch.nn.functional.interpolate(
            torch.as_tensor(rec.anchors.images[i]).permute(2, 0, 1)[None].float(), size=(height, width),
            mode="bilinear")[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()
        t0 = time.perf_counter()
        motion = model_online.advance(model, motion, emap, c2w)
        t1 = time.perf_counter()
        motion, colors, _, _ = model_online.correct(model, motion, image, c2w, intr, steps=steps, lr=lr,
                                                    scale=scale, colors=colors, colour_lr=colour_lr)
        t2 = time.perf_counter()
        if k:  # the first warms up
            preds.append(t1 - t0)
            fits.append(t2 - t1)
    return {"predict_s": float(np.median(preds)), "correct_s": float(np.median(fits)),
            "gaussians": len(model.gaussians), "control_points": model.control.num_points}


def online_drift(rows: list[dict], predictions: list[dict], path: Path, fit: str) -> None:
    """PSNR against time since training ended: the live render (corrected online anchors, projected onto
    the events since each frame) and before its projection, the chain never corrected, the same fits
    without events, the causal baselines (hold the last anchor; it projected onto the events; the events
    integrated onto it), and each new anchor frame against its prediction (bench.online);
    below, the same in 1 s bands (where "never worse than hold-last" is read)."""
    from matplotlib.figure import Figure

    from bench.figures import save

    fig = Figure(figsize=(9, 6.4), layout="constrained")
    ax, low = fig.subplots(2, 1, height_ratios=(3, 2), sharex=True)
    x = [r["since_end_s"] for r in rows]
    lines = (("live", f"live render (corrected, {fit}, projected onto the events)", "#1b6ca8"),
             ("live_model", "the same before the projection (the model alone)", "#8ab6d6"),
             ("no_corr", "no correction (events only)", "#d1495b"),
             ("no_events", "no events moving the anchors (corrections only)", "#7b4f9d"),
             ("hold_last", "hold last anchor frame", "#888888"),
             ("hold_projected", "that frame projected onto the events (no model)", "#c2a83e"),
             ("integrate", "events integrated onto the last anchor", "#66a182"))
    for key, label, colour in lines:
        ax.plot(x, [r[key] for r in rows], marker="o", ms=2.5, lw=1, color=colour, label=label)
    blend = [(r["since_end_s"], r["blend"]) for r in rows if r.get("blend") is not None]
    if blend:
        ax.plot([b[0] for b in blend], [b[1] for b in blend], ls="--", lw=1, color="#b07aa1",
                label="blend of the anchors either side (not causal)")
    ax.plot([p["since_end_s"] for p in predictions], [p["pred_psnr"] for p in predictions], ls="none",
            marker="x", color="#edae49", label="prediction vs the new anchor frame")
    ax.set_ylabel("PSNR (dB) vs held-out frame")
    ax.set_title("Online anchors past the checkpoint's span: drift")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    summary = bands(rows)
    edges = [b["from_s"] for b in summary] + [summary[-1]["to_s"]]
    for key, label, colour in lines:
        values = [b[key] for b in summary]
        low.stairs(values, edges, baseline=None, color=colour, label=label,
                   lw=2 if key in ("live", "hold_last") else 1.2)
    low.set_xlabel("time since training ended (s)")
    low.set_ylabel(f"mean PSNR per {BAND_S:g} s (dB)")
    low.grid(alpha=0.3)
    save(fig, path)


def main(argv=None) -> None:
    from edmcgs.protocol import TRANSITIONS
    from edmcgs.server.settings import Settings

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--recording", type=Path)
    p.add_argument("--checkpoint", type=Path)
    fit = Settings.model_fields  # the server's defaults
    p.add_argument("--steps", type=int, default=fit["online_fit_steps"].default, help="fit steps per anchor")
    p.add_argument("--scale", type=float, default=fit["online_fit_scale"].default, help="fit size")
    p.add_argument("--lr", type=float, default=fit["online_fit_lr"].default, help="fit step size")
    p.add_argument("--finetune-steps", type=int, default=fit["online_finetune_steps"].default,
                   help="g_phi fine-tune steps after each correction (0: off)")
    p.add_argument("--finetune-lr", type=float, default=fit["online_finetune_lr"].default)
    p.add_argument("--spawn", type=int, default=fit["online_spawn"].default,
                   help="Gaussians added per corrected anchor of a checkpoint drawn in anchor windows")
    p.add_argument("--colour-lr", type=float, default=fit["online_colour_lr"].default,
                   help="step size of the colour offsets each correction learns (0: off)")
    p.add_argument("--transition", choices=TRANSITIONS, default=fit["online_transition"].default,
                   help="what moves online anchors past the span (the server's online_transition)")
    p.add_argument("--no-project", action="store_true",
                   help="live renders are the model's alone (the server's online_project off)")
    p.add_argument("--timing-only", action="store_true", help="only the CPU figures (no drift)")
    p.add_argument("--plot", type=Path, help="the drift plot (PNG)")
    p.add_argument("--json", type=Path)
    p.add_argument("--csv", type=Path)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    results: dict = {"steps": args.steps, "scale": args.scale, "lr": args.lr,
                     "finetune_steps": args.finetune_steps, "finetune_lr": args.finetune_lr,
                     "spawn": args.spawn, "colour_lr": args.colour_lr, "transition": args.transition,
                     "project": not args.no_project}
    for w, h in ((173, 130), (346, 260)):
        t = timing(args.checkpoint, args.recording, w, h, args.steps, args.scale, args.lr, args.colour_lr)
        results[f"predict_ms_{w}x{h}"] = 1e3 * t["predict_s"]
        results[f"correct_ms_{w}x{h}"] = 1e3 * t["correct_s"]
        results[f"anchors_per_s_{w}x{h}"] = 1.0 / (t["predict_s"] + t["correct_s"])
        results[f"gaussians_{w}x{h}"] = t["gaussians"]
    if not args.timing_only:
        rows, extra = drift(args.recording, args.checkpoint, args.steps, args.scale, args.lr,
                            args.finetune_steps, args.finetune_lr, args.spawn, args.transition,
                            args.colour_lr, not args.no_project)
        for name in RENDERS:
            results[f"psnr_{name}"] = float(np.mean([r[name] for r in rows]))
        blend = [r["blend"] for r in rows if r["blend"] is not None]
        results["psnr_blend"] = float(np.mean(blend)) if blend else None
        for name in (*RENDERS, "blend"):
            # pooled over every moving pixel of every frame, as bench.traffic scores them
            results[f"psnr_{name}_moving"] = pooled([(r[f"{name}_moving"], r["moving_px"]) for r in rows
                                                     if r[f"{name}_moving"] is not None])
        results["live_minus_hold_last_worst_db"] = float(min(r["live"] - r["hold_last"] for r in rows))
        results["bands"] = bands(rows)
        results["live_minus_hold_last_worst_band_db"] = float(min(b["live"] - b["hold_last"]
                                                                  for b in results["bands"]))
        results["live_minus_hold_last_worst_band_pooled_db"] = float(min(
            b["live_pooled"] - b["hold_last_pooled"] for b in results["bands"]))
        results["frames_live_at_least_hold_last"] = sum(b["live_wins"] for b in results["bands"])
        results["pred_psnr"] = float(np.mean([r["pred_psnr"] for r in extra["pred"]]))
        results["corrected_psnr"] = float(np.mean([r["corrected_psnr"] for r in extra["pred"]]))
        chosen = [r["transition"] for r in extra["pred"]]
        results["transition_chosen"] = {name: chosen.count(name) for name in dict.fromkeys(chosen)}
        results["drift"] = rows
        results["predictions"] = extra["pred"]
        if args.csv is not None:
            args.csv.parent.mkdir(parents=True, exist_ok=True)
            with open(args.csv, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
        if args.plot is not None:
            args.plot.parent.mkdir(parents=True, exist_ok=True)
            online_drift(rows, extra["pred"], args.plot,
                         f"{args.steps} steps of {args.lr:g} at {args.scale:g}x size, "
                         f"colours at {args.colour_lr:g}")
    print(table(results, TARGETS))
    if "bands" in results:
        def cells(b, names, w=11):
            return "".join(f"{'-':>{w}}" if b[n] is None else f"{b[n]:>{w}.2f}" for n in names)

        names = (*RENDERS, "blend")
        print(f"\nmean PSNR (dB) per {BAND_S:g} s since training ended:\n{'band (s)':<10}"
              + "".join(f"{n:>15}" for n in names))
        for b in results["bands"]:
            print(f"{b['from_s']:g}-{b['to_s']:g}".ljust(10) + cells(b, names, 15))
        pooled_names = ("live_pooled", "hold_last_pooled", "blend_pooled")
        print(f"\npooled PSNR (dB, of the band's mean squared error) and frames live >= hold-last:\n"
              f"{'band (s)':<10}{'live':>11}{'hold_last':>11}{'blend':>11}{'live wins':>11}")
        for b in results["bands"]:
            print(f"{b['from_s']:g}-{b['to_s']:g}".ljust(10) + cells(b, pooled_names)
                  + f"{b['live_wins']:>6} / {b['frames']}")
    write_json(args.json, results)


if __name__ == "__main__":
    main()
