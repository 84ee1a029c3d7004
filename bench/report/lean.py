"""What each scene's checkpoint leaves out, and what that saves, measured side by side in one run.

A trained checkpoint (version 2) records what its scene does not need in ``meta["lean"]``
(``edmcgs.model.motion.leanness``): one channel for grey frames, the SH degree its views constrain, one
pose for a static camera, no event branch without events, frozen control points. Its *full twin* is the same
weights written as a checkpoint that leaves none of that out: nothing frozen (every Gaussian skinned),
three channels (a grey colour repeated), SH at the configured maximum (the higher coefficients zero: the
same image), the recording's whole trajectory for a static camera. The event branch cannot be added
back; a run trained without events is compared with the scene's full run instead (same query).

Measured on both, in one process: deform time per query at an anchor (the event branch skipped) and in
the middle of a gap (with its events), render time per frame, checkpoint bytes, and the error: the largest
distance between a lean and a full drawn Gaussian mean over every held-out time (against the freeze threshold,
the bound ``leanness`` states) and the PSNR of the lean render against the full one.
"""

from __future__ import annotations

import copy
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.report.render import pick_frame
from edmcgs.model.checkpoint import checksum, load_checkpoint, read_checkpoint, save_checkpoint
from edmcgs.model.config import EdmcgsConfig
from edmcgs.model.data import TrainingData
from edmcgs.model.dynamic import background_color
from edmcgs.model.eval.metrics import psnr
from edmcgs.model.motion.leanness import control_motion_bound
from edmcgs.model.render.sh import SH_C0
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.esim import luminance

PSNR_IDENTICAL = 100.0
"""``metrics.psnr``'s cap: the images are equal."""
DEFORM_REPEATS, RENDER_REPEATS = 10, 4
"""Timed repeats per the report's ``render_repeats``: a deform or a render here costs a few ms, and the
side-by-side differences are small against a shared machine's noise."""


# ------------------------------------------------------------------------------- the full twin

def full_twin_payload(payload: dict, trajectory) -> dict:
    """The checkpoint ``payload`` (``read_checkpoint``) with nothing left out but the event branch.

    trajectory: the recording's whole camera trajectory (restored where the checkpoint kept one pose).
    """
    twin = copy.deepcopy(payload)
    meta, state = twin["meta"], twin["state_dict"]
    meta["frozen"], meta["freeze_threshold"] = None, 0.0
    features = state["gaussians.features"]                                  # [N, K, C]
    degree, max_degree = int(meta["config"]["sh_degree"]), int(meta["lean"]["sh_degree"]["max"])
    if max_degree > degree:
        if features.shape[1] == 1:  # degree 0 stores colour logits; SH stores the DC coefficient
            features = (torch.sigmoid(features) - 0.5) / SH_C0
        pad = torch.zeros(features.shape[0], (max_degree + 1) ** 2 - features.shape[1], features.shape[2])
        features = torch.cat([features, pad], 1)
        meta["config"]["sh_degree"] = max_degree
    if meta["channels"] == 1:  # the grey colour and the grey background in all three channels
        features = features.repeat(1, 1, 3)
        grey = float(background_color(EdmcgsConfig.from_dict(meta["config"]), 1)[0])
        meta["channels"], meta["config"]["background"] = 3, [grey] * 3
    state["gaussians.features"] = features.contiguous()
    if meta["trajectory"] is not None and len(meta["trajectory"]["t_us"]) < len(trajectory.t_us):
        meta["trajectory"] = {"t_us": torch.from_numpy(np.asarray(trajectory.t_us, np.int64).copy()),
                              "c2w": torch.from_numpy(np.asarray(trajectory.c2w, np.float64).copy())}
    twin["checksum"] = checksum(twin)  # a new checkpoint: its own checksum
    return twin


def refrozen(path: Path, threshold: float, out: Path) -> Path:
    """The checkpoint at ``path`` written again with control points frozen at ``threshold``."""
    save_checkpoint(load_checkpoint(path), out, freeze_threshold=threshold)
    return out


# ------------------------------------------------------------------------------- measurements

def paired_ms(lean_fn, full_fn, repeats: int, warmup: int = 2) -> tuple[float, float]:
    """Median ms of each, timed alternately: on a shared machine both see the same load."""
    for _ in range(warmup):
        lean_fn(), full_fn()
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(repeats):
        for fn, out in ((lean_fn, times[0]), (full_fn, times[1])):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times[0]), 1000.0 * statistics.median(times[1])


def _queries(model, data: TrainingData) -> list[tuple[int, np.ndarray | None, np.ndarray, np.ndarray | None]]:
    """(t, event map, camera pose, held-out image) at every anchor and evaluable held-out time."""
    out = []
    for t in model.meta.anchors_us:
        out.append((int(t), None, data.trajectory.at(int(t)), None))
    for i in data.evaluable().tolist():
        t = int(data.held_out_t_us[i])
        tau = model.tau(t)
        emap = data.event_map(tau, t) if data.event_map is not None and t > tau else None
        out.append((t, emap, data.held_out_pose(i), data.held_out_images[i].astype(np.float32) / 255.0))
    return out


def deform_pair_ms(models, t: int, emap, data: TrainingData, repeats: int) -> tuple[float, float]:
    """``paired_ms`` of two models' deform at ``t`` with ``emap`` (a deform costs a few ms: more repeats)."""
    c2w = data.trajectory.at(t)
    return paired_ms(*[lambda m=m: m.deform(t, emap, c2w) for m in models], DEFORM_REPEATS * repeats)


def event_branch_ms(with_path: Path, without_path: Path, data: TrainingData, *, repeats: int) -> dict:
    """Deform ms of the scene's run with the event branch and the one trained without, timed alternately
    on the same queries: the mid-gap frame (with its events) and its anchor."""
    a, b = load_checkpoint(with_path), load_checkpoint(without_path)
    t_mid = int(data.held_out_t_us[pick_frame(a, data)])
    tau = a.tau(t_mid)
    out = {}
    for name, t, e in (("anchor", tau, None), ("mid", t_mid, data.event_map(tau, t_mid))):
        out[f"ms_{name}_with"], out[f"ms_{name}_without"] = deform_pair_ms((a, b), t, e, data, repeats)
    return out


def measure(label: str, lean_path: Path, data: TrainingData, *, repeats: int = 5,
            threads: int = 1) -> dict:
    """One row: the lean record of ``lean_path`` and its savings against the full twin (see the module
    docstring). ``data``: the recording's training arrays (events, held-out frames, trajectory)."""
    payload = read_checkpoint(lean_path)
    lean = load_checkpoint(lean_path)
    record, meta = payload["meta"]["lean"], lean.meta
    with tempfile.TemporaryDirectory() as tmp:
        twin_path = Path(tmp) / "full.ckpt"
        torch.save(full_twin_payload(payload, data.trajectory), twin_path)
        full_bytes = twin_path.stat().st_size
        full = load_checkpoint(twin_path)
    i = pick_frame(lean, data)
    t_mid = int(data.held_out_t_us[i])
    tau = lean.tau(t_mid)
    emap = data.event_map(tau, t_mid) if data.event_map is not None else None
    pose, k = data.held_out_pose(i), meta.intrinsics

    states = [m.deform(t_mid, emap, data.trajectory.at(t_mid)) for m in (lean, full)]
    render_ms = paired_ms(*[lambda m=m, st=st: m.render(st, pose, k, threads=threads)
                            for m, st in zip((lean, full), states, strict=True)], RENDER_REPEATS * repeats)
    anchor_ms = deform_pair_ms((lean, full), tau, None, data, repeats)
    mid_ms = deform_pair_ms((lean, full), t_mid, emap, data, repeats)

    worst, psnr_full, truth_lean, truth_full = 0.0, PSNR_IDENTICAL, [], []
    for t, e, c2w, image in _queries(lean, data):
        ls, fs = lean.deform(t, e, data.trajectory.at(t)), full.deform(t, e, data.trajectory.at(t))
        drawn = fs.opacities.reshape(-1) > 0  # other anchor windows' Gaussians are not drawn
        shift = (ls.means - fs.means)[drawn].norm(dim=-1)
        worst = max(worst, float(shift.max()) if len(shift) else 0.0)
        li, fi = lean.render(ls, c2w, k, threads=threads), full.render(fs, c2w, k, threads=threads)
        psnr_full = min(psnr_full, psnr(np.broadcast_to(li, fi.shape), fi))
        if image is not None:
            truth_lean.append(psnr(li, image))
            truth_full.append(psnr(fi[..., : image.shape[2]], image))
    frozen = record.get("frozen") or {}
    threshold = float(meta.freeze_threshold)
    bound = control_motion_bound(lean)
    return {
        "label": label,
        "channels": int(meta.channels),
        "channels_why": record["channels"]["why"],
        "sh_degree": int(record["sh_degree"]["value"]),
        "sh_max": int(record["sh_degree"]["max"]),
        "sh_why": record["sh_degree"]["why"],
        "static_camera": bool(record["static_camera"]["value"]),
        "trajectory_poses": 0 if meta.trajectory is None else len(meta.trajectory.t_us),
        "event_branch": bool(meta.has_event_branch),
        "frozen_points": int(frozen.get("control_points", 0)),
        "control_points": lean.control.num_points,
        "still_gaussians": int(frozen.get("gaussians_still", 0)),
        "gaussians": len(lean.gaussians),
        "threshold": threshold,
        "threshold_of_extent": threshold / float(lean.extent),
        "least_motion_of_extent": float(bound.min()) / float(lean.extent),
        "anchor_us": tau, "mid_us": t_mid,
        "mid_events": 0 if emap is None else int(np.abs(emap).sum()),
        "ms_deform_anchor_lean": anchor_ms[0],
        "ms_deform_anchor_full": anchor_ms[1],
        "ms_deform_mid_lean": mid_ms[0],
        "ms_deform_mid_full": mid_ms[1],
        "ms_render_lean": render_ms[0],
        "ms_render_full": render_ms[1],
        "bytes_lean": lean_path.stat().st_size,
        "bytes_full": full_bytes,
        "max_mean_shift": worst,
        "within_threshold": bool(worst <= threshold * (1 + 1e-4) + 1e-6),
        "psnr_lean_vs_full": psnr_full,
        "psnr_truth_lean": float(np.mean(truth_lean)) if truth_lean else None,
        "psnr_truth_full": float(np.mean(truth_full)) if truth_full else None,
        "times": len(_queries(lean, data)),
    }


# ------------------------------------------------------------------------------- a grey scene

def grey_recording(rec: Recording) -> Recording:
    """``rec`` with its frames as a DAVIS346's APS would give them: one channel, Rec. 601 luminance (the
    quantity the simulator made the events from)."""
    def grey(frames: Frames | None) -> Frames | None:
        if frames is None:
            return None
        images = np.stack([np.round(luminance(img) * 255.0) for img in frames.images]).astype(np.uint8)
        return Frames(frames.t_us, images[..., None], frames.poses)

    meta = dict(rec.metadata) | {"grey": "Rec. 601 luminance of the RGB frames"}
    return Recording(width=rec.width, height=rec.height, events=rec.events, anchors=grey(rec.anchors),
                     held_out=grey(rec.held_out), intrinsics=rec.intrinsics,
                     trajectory_t_us=rec.trajectory_t_us, trajectory_c2w=rec.trajectory_c2w,
                     contrast_threshold=rec.contrast_threshold, sensor=rec.sensor, metadata=meta)


# ------------------------------------------------------------------------------- Markdown

def _psnr_text(value: float | None) -> str:
    if value is None:
        return "—"
    return "identical" if value >= PSNR_IDENTICAL else f"{value:.2f}"


def _versus(lean: float, full: float, fmt: str = ".2f") -> str:
    """"lean / full (change)": a negative change is what leaving things out saved."""
    change = f" ({100 * (lean / full - 1):+.0f} %)" if full > 0 else ""
    return f"{lean:{fmt}} / {full:{fmt}}{change}"


def left_out_table(rows: list[dict]) -> list[str]:
    lines = ["| run | channels | SH degree (max): why | camera | event branch | frozen points | still "
             "Gaussians | threshold (% extent) | least motion (% extent) |", "|---|---|---|---|---|---:|---:|"
             "---:|---:|"]
    for r in rows:
        camera = "static: 1 pose" if r["static_camera"] else f"moves: {r['trajectory_poses']} poses"
        lines.append(f"| {r['label']} | {r['channels']} ({r['channels_why']}) | {r['sh_degree']} "
                     f"({r['sh_max']}): {r['sh_why']} | {camera} | {'yes' if r['event_branch'] else 'no'} | "
                     f"{r['frozen_points']} / {r['control_points']} | {r['still_gaussians']} / "
                     f"{r['gaussians']} | {100 * r['threshold_of_extent']:.2f} | "
                     f"{100 * r['least_motion_of_extent']:.2f} |")
    return lines


def saved_table(rows: list[dict]) -> list[str]:
    lines = ["| run | deform at anchor ms, lean / full | deform mid-gap ms, lean / full (events) | "
             "render ms, lean / full | checkpoint kB, lean / full | max mean shift (threshold) | PSNR lean "
             "vs full, worst of N times | held-out PSNR lean / full |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        held = f"{_psnr_text(r['psnr_truth_lean'])} / {_psnr_text(r['psnr_truth_full'])}"
        ok = "" if r["within_threshold"] else " **beyond**"
        lines.append(f"| {r['label']} | {_versus(r['ms_deform_anchor_lean'], r['ms_deform_anchor_full'])} | "
                     f"{_versus(r['ms_deform_mid_lean'], r['ms_deform_mid_full'])} ({r['mid_events']}) | "
                     f"{_versus(r['ms_render_lean'], r['ms_render_full'])} | "
                     f"{_versus(r['bytes_lean'] / 1e3, r['bytes_full'] / 1e3, '.1f')} | "
                     f"{r['max_mean_shift']:.2e} ({r['threshold']:.2e}){ok} | "
                     f"{_psnr_text(r['psnr_lean_vs_full'])}, {r['times']} | {held} |")
    return lines


def _notes(by: dict[str, dict], context: dict) -> list[str]:
    """Sentences comparing rows: the event branch, grey, frozen points, the static camera."""
    notes = []
    full, noev = by.get(context.get("full_label")), by.get(context.get("no_events_label"))
    ev = context.get("event_branch")
    if full is not None and noev is not None and ev is not None:
        notes.append(
            f"- Event branch (the two runs timed alternately): the mid-gap query deforms in "
            f"{ev['ms_mid_with']:.2f} ms with it ({full['mid_events']} events) and "
            f"{ev['ms_mid_without']:.2f} ms in the run trained without events (no event branch: "
            "`edmcgs-serve --checkpoint CKPT` serves it without a sensor); at the anchor the branch is "
            f"skipped ({ev['ms_anchor_with']:.2f} / "
            f"{ev['ms_anchor_without']:.2f} ms). Held-out PSNR {_psnr_text(full['psnr_truth_lean'])} / "
            f"{_psnr_text(noev['psnr_truth_lean'])} dB.")
    grey = by.get(context.get("grey_label"))
    if grey is not None:
        notes.append(
            f"- Grey: `{grey['label']}` stores {grey['bytes_lean'] / 1e3:.0f} kB against "
            f"{grey['bytes_full'] / 1e3:.0f} kB for its RGB twin and renders in "
            f"{grey['ms_render_lean']:.2f} ms against {grey['ms_render_full']:.2f} ms (images: "
            f"{_psnr_text(grey['psnr_lean_vs_full'])}; held-out PSNR of the grey run "
            f"{_psnr_text(grey['psnr_truth_lean'])} dB).")
    frozen = by.get(context.get("refrozen_label"))
    if frozen is not None and full is not None:
        pct = 100 * full["threshold_of_extent"]
        held = "held" if frozen["within_threshold"] else "**not held**"
        notes.append(
            f"- Frozen control points: at the default threshold ({pct:.2f} % of the extent) "
            f"`{full['label']}` freezes {full['frozen_points']} of {full['control_points']} points: the "
            "least-moving one moves "
            f"{100 * full['least_motion_of_extent']:.2f} % of the extent over the span. `{frozen['label']}` "
            f"freezes the same weights at a stated, looser threshold "
            f"({100 * frozen['threshold_of_extent']:.2f} % of the extent: the median point's motion) to "
            "measure the mechanism: "
            f"{frozen['still_gaussians']} of {frozen['gaussians']} Gaussians still, means within "
            f"{frozen['max_mean_shift']:.2e} of the full path (bound {frozen['threshold']:.2e}: {held}).")
    if not any(r["static_camera"] for r in by.values()):
        notes.append("- Static camera: every scene here has a moving camera (its trajectory is kept); a "
                     "static one is stored as one pose and skips interpolation "
                     "(`tests/model/test_checkpoint_lean.py`).")
    return notes


def section(rows: list[dict], context: dict) -> list[str]:
    """The summary's section on what the checkpoints leave out."""
    if not rows:
        return []
    return [
        "## 5. What each scene leaves out", "",
        "Each trained checkpoint (version 2) records what its scene does not need (`meta.lean`, decided from "
        "the data when it was saved). Its *full twin* is the same weights leaving nothing out: every "
        "Gaussian skinned, three channels, SH at the configured maximum (higher coefficients zero), the "
        "whole trajectory; both are measured here in one process, on the mid-gap held-out frame farthest "
        f"from its anchor and at that anchor ({context['threads']} thread(s); medians of "
        f"{DEFORM_REPEATS * context['repeats']} deforms and {RENDER_REPEATS * context['repeats']} renders, "
        "lean and full timed alternately; a negative change is a saving). The error is taken over every "
        "anchor and held-out time: the largest "
        "distance between a lean and a full Gaussian mean (the stated bound: the freeze threshold) and the "
        "worst PSNR of the lean render against the full one. Where a row leaves out nothing its twin adds "
        "back (nothing frozen, the same channels and SH), both do the same work: their difference is the "
        "timing noise of this shared machine. `lean.csv` has every number.", "",
        *left_out_table(rows), "", *saved_table(rows), "",
        *_notes({r["label"]: r for r in rows}, context), "",
    ]


# ------------------------------------------------------------------------------- the report's rows

def median_threshold(path: Path) -> float:
    """The median control point's motion bound (world units): a threshold that freezes about half."""
    return float(control_motion_bound(load_checkpoint(path)).median())


def lean_rows(entries: list[tuple[str, Path, TrainingData]], *, repeats: int, threads: int,
              progress: bool = False) -> list[dict]:
    """``measure`` for each (label, checkpoint, training arrays)."""
    from tqdm import tqdm

    return [measure(label, path, data, repeats=repeats, threads=threads)
            for label, path, data in tqdm(entries, desc="lean checkpoints", disable=not progress)]
