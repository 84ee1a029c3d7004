"""The stability section's slow cases, on the report's trained models and real benchmark scenes.

Each row says what it checks and what came out; ``ok`` is whether the stated check held. The fast cases
live in ``tests/stability`` (and a few in other areas' tests); ``TEST_CASES`` lists them so that the
report's table shows where every stability case is checked.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from bench.report.render import pick_frame, state_arrays
from edmcgs.geometry import pose_from_quat, project, world_to_camera
from edmcgs.model.dynamic import EdMCGS, background_color
from edmcgs.model.eval.metrics import psnr
from edmcgs.model.render import reference as reference_render
from edmcgs.model.render.rasterize import rasterize
from edmcgs.model.render.rasterize_fast import rasterize_fast
from edmcgs.pipeline import training_data
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording
from edmcgs.synth.scene import make_scene

TEST_CASES = [
    ("stiff motion", "half-frame crossing between two anchors at 10 fps: finite losses, params, renders",
     "tests/model/test_model.py::test_stiff_motion_trains_without_nan_or_inf"),
    ("stiff motion", "the same crossing with anchors 0.5 s and 1 s apart (2 and 1 fps)",
     "tests/stability/test_sparse_anchors.py"),
    ("empty window", "at an anchor: exactly the anchor state", "tests/model/test_model.py::"
     "test_empty_window_at_an_anchor_is_exactly_the_anchor_state"),
    ("empty window", "between anchors: exactly the prior's state, event displacement None",
     "tests/stability/test_event_windows.py::test_empty_window_between_anchors_adds_exactly_nothing"),
    ("10^7-event burst", "I_E equals the int64 bincount per pixel; deform finite; renders in [0, 1]",
     "tests/stability/test_event_windows.py::test_a_burst_of_ten_million_events_sums_exactly_and_deforms_finite"),
    ("hot pixels only", "finite; only control points within Phi's receptive field of a hot pixel move; "
     "training on noise-only windows stays finite", "tests/stability/test_event_windows.py"),
    ("saturated frames", "simulator: black <-> white frames give finite events",
     "tests/synth/test_esim.py::test_saturated_black_and_white_frames_stay_finite"),
    ("saturated frames", "event loss and gradients finite at log(0 + eps); training on black/white "
     "anchors finite", "tests/stability/test_saturated_frames.py"),
    ("24 h of epoch µs", "normalised time, tau, ring windows, trajectory, training grid resolve 1 µs "
     "at 1.7e15 µs over a day", "tests/stability/test_epoch_time.py"),
    ("poses at the limits", "Gaussians behind / on the near plane culled, no NaN (both rasterizers)",
     "tests/raster/test_rasterize*.py::test_behind_the_camera_*"),
    ("poses at the limits", "camera inside Gaussians, edge-on discs, a floor from 1 cm above, splats "
     "50x outside the frustum, grazing orbit: both paths match the float64 reference",
     "tests/stability/test_extreme_poses.py"),
    ("precision", "float32 vs float64 on benchmark scenes: max <= 1e-3, mean <= 1e-6",
     "tests/stability/test_precision.py"),
]
"""(case, what is checked, where) of the fast cases in the test suite."""


def _row(case: str, check: str, result: str, ok: bool) -> dict:
    return {"case": case, "check": check, "result": result, "ok": bool(ok), "where": "report"}


def _finite_state(state) -> bool:
    fields = (state.means, state.quats, state.scales, state.opacities, state.colors)
    return all(bool(torch.isfinite(t).all()) for t in fields)


def anchor_gap_motion(rec: Recording) -> float:
    """How far the scene moves on screen away from what its last anchor shows: the largest, over the held-out
    times, 99th percentile (over the Gaussians in front of the camera) of the image displacement of the
    scene's Gaussians since the anchor, as a fraction of the image width."""
    scene = make_scene(rec.metadata["scene"], rec.metadata["size"])
    k = scene.intrinsics

    def screen(t_us: int):
        t_s = t_us * 1e-6
        means = scene.gaussians_at(t_s).means.astype(np.float64)
        return project(means, world_to_camera(scene.camera_at(t_s)), k)

    anchors = rec.anchors.t_us
    worst = 0.0
    for t in rec.held_out.t_us.tolist():
        (uv0, z0), (uv1, z1) = screen(int(anchors[np.searchsorted(anchors, t, side="right") - 1])), screen(t)
        front = (z0 > 0) & (z1 > 0)
        worst = max(worst, float(np.percentile(np.linalg.norm(uv1 - uv0, axis=1)[front], 99)))
    return worst / k.width


def sparse_anchor_rows(runs: dict[float, dict], model_at: dict[float, EdMCGS], recs: dict[float, Recording],
                       baseline: dict[float, dict]) -> list[dict]:
    """Anchors 1-2 s apart: every loss finite, every held-out state finite; the PSNR loss against the
    table's rates (``baseline``: fps -> full-model run) measured."""
    rows = []
    for fps, run in sorted(runs.items()):
        model, data = model_at[fps], training_data(recs[fps])
        finite = True
        for i in data.evaluable().tolist():
            t = int(data.held_out_t_us[i])
            tau = model.tau(t)
            emap = data.event_map(tau, t) if t > tau else None
            finite &= _finite_state(model.deform(t, emap, data.trajectory.at(t)))
        ok = run["nonfinite_steps"] == 0 and finite and np.isfinite(run["psnr"])
        motion = anchor_gap_motion(recs[fps])
        versus = ", ".join(f"{run['psnr'] - base['psnr']:+.2f} dB vs {f:g} fps"
                           for f, base in sorted(baseline.items()))
        result = (f"{run['nonfinite_steps']} non-finite steps of {run['iterations']}; {run['frames']} "
                  f"held-out states finite: {finite}; PSNR {run['psnr']:.2f} dB ({versus})")
        check = (f"gaps of {1000 / fps:.0f} ms, in which the figure moves up to {100 * motion:.0f} % of the "
                 "image width away from its anchor: finite losses and held-out states; PSNR loss measured")
        rows.append(_row(f"anchors at {fps:g} fps", check, result, ok))
    return rows


def _burst(n: int, t0: int, t1: int, width: int, height: int, seed: int = 0) -> Events:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n, dtype=np.int64) * (t1 - t0) // n
    x = rng.integers(0, width, n).astype(np.uint16)
    y = rng.integers(0, height, n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.7, 1, -1).astype(np.int8)
    return Events(t, x, y, p)


def _raw_render(state, w2c: np.ndarray, k, bg: np.ndarray, fast: bool) -> np.ndarray:
    if fast:
        return rasterize_fast(*state_arrays(state), w2c.astype(np.float32), k, background=bg).image
    return rasterize(state.means, state.quats, state.scales, state.opacities, state.colors, w2c, k,
                     background=torch.as_tensor(bg)).image.numpy()


def event_window_rows(model: EdMCGS, rec: Recording) -> list[dict]:
    """At the held-out frame farthest from its anchor: the real window, an empty one, 10^7 random events,
    hot-pixel noise only; PSNR against the ground-truth frame for each."""
    data = training_data(rec)
    i = pick_frame(model, data)
    t = int(data.held_out_t_us[i])
    tau = model.tau(t)
    w, h = data.event_size
    c2w, ev_c2w = data.held_out_pose(i), data.trajectory.at(t)
    w2c = world_to_camera(c2w)
    k = model.meta.intrinsics
    bg = background_color(model.config, model.meta.channels).numpy()
    target = data.held_out_images[i].astype(np.float32) / 255.0
    extent = float(model.extent)

    def score(emap):
        state = model.deform(t, emap, ev_c2w)
        image = _raw_render(state, w2c, k, bg, fast=True)
        ok = _finite_state(state) and np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
        return state, psnr(np.clip(image, 0, 1), target), ok

    real = data.event_map(tau, t)
    real_state, real_psnr, real_ok = score(real)
    _, empty_psnr, empty_ok = score(np.zeros((h, w), np.float32))
    where = f"frame {i}, {(t - tau) / 1000:.0f} ms after its anchor, {int(np.abs(real).sum())} real events"
    rows = [_row("empty window (trained model)", f"{where}: the prior alone; PSNR vs the real window",
                 f"{empty_psnr:.2f} dB without events vs {real_psnr:.2f} dB with them "
                 f"({real_psnr - empty_psnr:+.2f} dB from the events)", empty_ok and real_ok)]

    n = 10_000_000
    burst = _burst(n, tau, t, w, h)
    t0 = time.perf_counter()
    emap = accumulate(burst, w, h)
    ms = 1000 * (time.perf_counter() - t0)
    flat = burst.y.astype(np.int64) * w + burst.x
    exact = np.bincount(flat[burst.p > 0], minlength=w * h) - np.bincount(flat[burst.p < 0], minlength=w * h)
    sums_ok = np.array_equal(emap.reshape(-1).astype(np.int64), exact)
    state, burst_psnr, ok = score(emap)
    moved = float((state.means - real_state.means).norm(dim=1).max()) / extent
    rows.append(_row("10^7-event burst (trained model)", "I_E exact integer sums; deform finite; render "
                     "finite in [0, 1]; PSNR and displacement measured",
                     f"accumulate {ms:.0f} ms, exact: {sums_ok}; PSNR {burst_psnr:.2f} dB "
                     f"({burst_psnr - real_psnr:+.2f} vs the real window); Gaussians moved up to "
                     f"{moved:.3g} scene extents", ok and sums_ok))

    rng = np.random.default_rng(1)
    hot = np.zeros((h, w), np.float32)
    idx = rng.choice(w * h, 20, replace=False)
    hot.reshape(-1)[idx] = rng.choice([-1.0, 1.0], 20) * 500.0
    _, hot_psnr, ok = score(hot)
    rows.append(_row("hot pixels only (trained model)", "20 pixels with +-500 net events, no real events: "
                     "finite; PSNR vs the empty window measured",
                     f"PSNR {hot_psnr:.2f} dB vs {empty_psnr:.2f} dB empty "
                     f"({hot_psnr - empty_psnr:+.2f} dB)", ok))
    return rows


def pose_rows(model: EdMCGS, rec: Recording) -> list[dict]:
    """The trained model's state at mid-sequence, from a camera inside it, facing away, and grazing."""
    data = training_data(rec)
    t = int((model.meta.t_start_us + model.meta.t_end_us) // 2)
    state = model.deform(t)
    k = model.meta.intrinsics
    bg = background_color(model.config, model.meta.channels).numpy()
    base = data.trajectory.at(t)
    inside = base.copy()
    inside[:3, 3] = state.means[int(torch.argmax(state.opacities))].numpy()
    away = base @ pose_from_quat([0, 0, 0], [0.0, 0.0, 1.0, 0.0])
    centre = model.center.numpy().astype(np.float64)
    angle = np.deg2rad(89.0)
    tilt = pose_from_quat([0, 0, 0], [np.cos(angle / 2), np.sin(angle / 2), 0, 0])
    about = np.eye(4)
    about[:3, :3] = tilt[:3, :3]
    orbit = about @ np.block([[np.eye(3), -centre[:, None]], [np.zeros((1, 3)), 1]]) @ base
    orbit[:3, 3] += centre
    rows = []
    for name, c2w in (("camera inside the brightest Gaussian", inside), ("facing away (all behind)", away),
                      ("orbited 89 degrees about the scene's centre (grazing)", orbit)):
        w2c = world_to_camera(c2w)
        fast, slow = (_raw_render(state, w2c, k, bg, fast=f) for f in (True, False))
        ref = reference_render.render_camera(state_arrays(state), w2c, k, background=bg)[0]
        ok = all(np.isfinite(img).all() and img.min() >= -1e-6 and img.max() <= 1 + 1e-6
                 for img in (fast, slow))
        errs = [float(np.abs(img - ref).max()) for img in (fast, slow)]
        rows.append(_row(f"pose: {name}", "both rasterizers finite, in [0, 1], within 1e-3 of the float64 "
                         "reference",
                         f"range [{min(fast.min(), slow.min()):.3f}, {max(fast.max(), slow.max()):.3f}], "
                         f"max abs error numba {errs[0]:.1e}, torch {errs[1]:.1e}", ok and max(errs) <= 1e-3))
    return rows


def precision_rows(scenes: list[str], size: str, *, t_s: float = 0.5) -> list[dict]:
    """float32 renders (numba, torch) of each scene's own Gaussians against the float64 reference."""
    rows = []
    for name in scenes:
        scene = make_scene(name, size)
        g = scene.gaussians_at(t_s)
        arrays = [np.asarray(a) for a in (g.means, g.quats, g.scales, g.opacities, g.colors)]
        w2c, k = world_to_camera(scene.camera_at(t_s)), scene.intrinsics
        bg = np.asarray(scene.background)
        refs = {t_min: reference_render.render_camera(arrays, w2c, k, background=bg, t_min=t_min)[0]
                for t_min in (1e-4, 0.0)}
        cells = []
        ok = True
        for t_min, ref in refs.items():
            fast = rasterize_fast(*arrays, w2c.astype(np.float32), k, background=bg.astype(np.float32),
                                  t_min=t_min).image
            d = np.abs(fast - ref)
            cells.append(f"numba t_min={t_min:g}: max {d.max():.1e}, mean {d.mean():.1e}")
            ok &= d.max() <= 1e-3
        torch32 = rasterize(*(torch.tensor(a, dtype=torch.float32) for a in arrays), w2c, k,
                            background=torch.tensor(bg, dtype=torch.float32)).image.numpy()
        d = np.abs(torch32 - refs[1e-4])
        cells.append(f"torch: max {d.max():.1e}, mean {d.mean():.1e}")
        ok &= d.max() <= 1e-3
        rows.append(_row(f"precision: {name} ({len(g.means)} Gaussians)", "float32 vs the float64 reference, "
                         "max <= 1e-3", "; ".join(cells), ok))
    return rows
