"""Render error against render time per frame, across the fast path's knobs, on a trained model.

One held-out frame (the one farthest from its anchor near the middle of the sequence) is deformed by the
trained model and rendered by ``rasterize_fast`` with one knob changed at a time:

- opacity threshold: Gaussians below it are pruned before rendering (the count kept is reported);
- control points: a farthest-point subset of the trained ones, the Gaussians re-bound to it (a post-hoc
  reduction: the deformation is evaluated at fewer points, the skinning spans larger distances);
- resolution: the same camera at a fraction of the scene's size;
- early termination: ``alpha_min`` (splats fainter than it are skipped) and ``t_min`` (a pixel stops
  when its transmittance would fall below it).

Each setting is scored against the float64 brute-force reference renderer of the test suite
(``model/render/reference.py``; same resolution, all Gaussians and control points, default knobs: the
model's exact image) and against the ground truth (the synthetic scene's own Gaussians rendered at
that resolution). Times are medians over repeats; a frame's time is deform + render.
"""

from __future__ import annotations

import copy
import statistics
import time

import numpy as np
import torch
from tqdm import tqdm

from edmcgs.geometry import world_to_camera
from edmcgs.model.dynamic import EdMCGS, background_color
from edmcgs.model.eval.metrics import psnr, ssim_score
from edmcgs.model.motion.control_points import ControlPoints
from edmcgs.model.motion.neighbors import farthest_point_sampling, knn
from edmcgs.model.render import reference as reference_render
from edmcgs.model.render.rasterize_fast import rasterize_fast
from edmcgs.pipeline import training_data
from edmcgs.sensor.files.recording import Recording
from edmcgs.synth.scene import make_scene

OPACITY_THRESHOLDS = (0.0, 0.01, 0.03, 0.1, 0.2, 0.4)
CONTROL_DIVISORS = (1, 2, 4, 8, 16, 32)
ALPHA_MINS = (0.0, 1 / 255, 0.01, 0.03, 0.1)
T_MINS = (0.0, 1e-4, 1e-3, 1e-2, 0.1)
DEFAULT_KNOBS = {"alpha_min": 1 / 255, "t_min": 1e-4}


def median_ms(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):  # JIT, caches, allocator
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def with_fewer_control_points(model: EdMCGS, m: int) -> EdMCGS:
    """A copy of ``model`` whose control points are a farthest-point subset of ``m`` of its own."""
    reduced = copy.deepcopy(model)
    cp = model.control
    idx = farthest_point_sampling(cp.positions, m)
    positions = cp.positions[idx].clone()
    graph = knn(positions, positions, min(cp.graph.shape[1], m - 1), exclude_self=True)[1]
    bind = knn(model.gaussians.means.detach(), positions, min(cp.bind.shape[1], m))[1]
    reduced.control = ControlPoints(positions, cp.log_radius.detach()[idx].clone(), graph, bind)
    reduced.meta.frozen = None  # the checkpoint's mask is of the original points; these are not bounded
    return reduced


def pick_frame(model: EdMCGS, data) -> int:
    """The evaluable held-out frame farthest from its anchor, nearest the middle of the sequence."""
    idx = data.evaluable()
    t = data.held_out_t_us[idx]
    since = np.array([int(ti) - model.tau(int(ti)) for ti in t])
    middle = np.abs(t - (t[0] + t[-1]) / 2)
    return int(idx[np.lexsort((middle, -since))[0]])


def state_arrays(state) -> list[np.ndarray]:
    return [t.detach().cpu().numpy() for t in (state.means, state.quats, state.scales, state.opacities,
                                               state.colors)]


def render_sweep(model: EdMCGS, rec: Recording, *, scales: tuple[float, ...], repeats: int,
                 progress: bool = True) -> tuple[list[dict], dict]:
    """(rows, context): one row per knob setting; context names the frame and the baselines."""
    data = training_data(rec)
    i = pick_frame(model, data)
    t_us = int(data.held_out_t_us[i])
    tau = model.tau(t_us)
    emap = None
    if data.event_map is not None and t_us > tau:
        emap = np.asarray(data.event_map(tau, t_us), np.float32)
    ev_c2w = data.trajectory.at(t_us)
    c2w = data.held_out_pose(i)
    w2c64 = world_to_camera(c2w)
    w2c = w2c64.astype(np.float32)
    base_k = model.meta.intrinsics
    bg = background_color(model.config, model.meta.channels).numpy()
    scene = make_scene(rec.metadata["scene"], rec.metadata["size"])
    t_s = t_us * 1e-6  # synthetic recordings count microseconds from the scene's t = 0
    if not np.allclose(scene.camera_at(t_s), c2w, atol=1e-9):
        raise RuntimeError("the recording's held-out pose is not the scene's camera: not a synth recording?")
    gt_cloud = scene.gaussians_at(t_s)

    def deform(m: EdMCGS):
        return m.deform(t_us, emap, ev_c2w)

    m_full = model.control.num_points
    reduced = {m: with_fewer_control_points(model, m) if m < m_full else model
               for m in (m_full // d for d in CONTROL_DIVISORS) if m > model.config.skin_k}

    state = deform(model)
    arrays = state_arrays(state)
    deform_ms = {m: median_ms(lambda r=r: deform(r), repeats) for m, r in reduced.items()}
    ms_deform = deform_ms[m_full]
    refs, gts = {}, {}

    def truth(k):
        if k.width not in refs:
            refs[k.width] = reference_render.render_camera(arrays, w2c64, k, background=bg)[0]
            gt = rasterize_fast(gt_cloud.means, gt_cloud.quats, gt_cloud.scales, gt_cloud.opacities,
                                gt_cloud.colors, w2c, k, background=np.asarray(scene.background, np.float32))
            gts[k.width] = np.clip(gt.image, 0.0, 1.0)
        return refs[k.width], gts[k.width]

    def row(knob: str, value, arr, k, deform_ms: float, control_points: int, **knobs) -> dict:
        opts = DEFAULT_KNOBS | knobs

        def render():
            return rasterize_fast(*arr, w2c, k, background=bg, **opts)

        ms = median_ms(render, repeats)
        image = np.clip(render().image, 0.0, 1.0)
        ref, gt = truth(k)
        return {"knob": knob, "value": value, "gaussians": int(arr[0].shape[0]),
                "control_points": control_points,
                "width": k.width, "height": k.height, "alpha_min": opts["alpha_min"], "t_min": opts["t_min"],
                "ms_deform": deform_ms, "ms_render": ms, "ms_frame": deform_ms + ms,
                "rmse_ref": float(np.sqrt(np.mean((image - ref) ** 2))),
                "max_abs_ref": float(np.abs(image - ref).max()),
                "psnr_gt": psnr(image, gt), "ssim_gt": ssim_score(image, gt)}

    total = len(OPACITY_THRESHOLDS) + len(reduced) + len(scales) + len(ALPHA_MINS) + len(T_MINS)
    rows = []
    with tqdm(total=total, desc="render knobs", disable=not progress, leave=False) as bar:
        for thr in OPACITY_THRESHOLDS:
            keep = arrays[3] >= thr
            rows.append(row("opacity threshold", thr, [a[keep] for a in arrays], base_k, ms_deform, m_full))
            bar.update()
        for m, r in reduced.items():
            rows.append(row("control points", m, state_arrays(deform(r)), base_k, deform_ms[m], m))
            bar.update()
        for s in scales:
            k = base_k.scaled(max(1, round(base_k.width * s)), max(1, round(base_k.height * s)))
            rows.append(row("resolution", s, arrays, k, ms_deform, m_full))
            bar.update()
        for a in ALPHA_MINS:
            rows.append(row("alpha_min", a, arrays, base_k, ms_deform, m_full, alpha_min=a))
            bar.update()
        for tm in T_MINS:
            rows.append(row("t_min", tm, arrays, base_k, ms_deform, m_full, t_min=tm))
            bar.update()
    held = data.held_out_images[i].astype(np.float32) / 255.0
    context = {"frame": i, "t_us": t_us, "anchor_us": tau, "ms_since_anchor": (t_us - tau) / 1000,
               "events": 0 if emap is None else int(np.abs(emap).sum()), "gaussians": len(state),
               "control_points": m_full, "width": base_k.width, "height": base_k.height,
               "gt_vs_held_out_psnr": psnr(truth(base_k)[1], held), "threads": torch.get_num_threads()}
    return rows, context
