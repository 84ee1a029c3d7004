"""Poses from a recording's own frames (``edmcgs.poses``, as ``edmcgs poses`` / ``--poses auto`` run it):
frames registered, trajectory error against the true poses, time.

    .venv/bin/python -m bench.poses [--json PATH] [--quick] [--recording REC ...] [--scenes a,b] [--repeat N]

Scenes (``--scenes``, default all):

- ``jumpingjack-sweep``, ``jumpingjack-orbit``: the frames of ``edmcgs synth jumpingjack --camera
  sweep|orbit --duration 4`` (small, 173x130, 25 frames per second: the anchors and held-out frames
  together; rendered here, sharp, without the event simulation the frames do not need), the camera
  given; a figure that never stops moving in front of a plain background, and the IMU the recording of
  ``edmcgs synth jumpingjack --seed 0`` holds (``synth.build.scene_imu``: 1 kHz, ``ImuConfig``'s noise and
  a bias drawn per axis).
  Nothing in view is static: the frames alone can at best follow the figure's torso, which bobs by up to
  0.17 m with each jump (0.87 % of the 4 s path after the alignment); the IMU measures the camera.
- ``rigid-small``: ``lego`` frozen at one instant along its arc (``harness.pose_scenes``; the
  scene of the pose test), 26 frames, 173x130, the camera given.
- ``rigid-60``: the same at 346x260, 60 frames at 25 Hz (the time target: <= 2 min on 2 cores).
- ``traffic-pan``: ``edmcgs synth traffic-pan``'s street (cars crossing; 346x260, 60 frames at 25 Hz,
  the pan at its 12 px/s), sharp and noiseless; the camera estimated. A pan has no parallax: rotations
  only, scored by their error.
- ``test-frame``: ``tests/data/test-frame.aedat4``, a real handheld DAVIS346 recording (20 APS frames,
  no calibration: the camera is estimated); no truth, so frames registered only.
- ``--recording REC``: any recording (e.g. ``edmcgs synth street3d``), its camera and its true poses
  (the frames' poses, else its trajectory) when it has them.

Per scene: frames, frames registered in the kept model, the absolute trajectory error after a Sim(3)
alignment (evo; metres of the scene and % of the true path length; not for a camera that only turns;
with the IMU fused when the scene has one, and from the frames alone beside it),
the largest rotation error of a frame relative to the first (degrees), wall and CPU seconds of the
estimate (CPU: every thread of this process, i.e. COLMAP's). With ``--repeat N`` each scene is estimated
N times (COLMAP's threads make runs differ): the row is the run with the median error, beside every
run's error and the largest. Targets: ATE <= 1 % of the path, >= 95 %
of a real recording's frames registered, ``rigid-60`` within 120 s wall.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.results import table, write_json
from edmcgs.errors import EdmcgsError
from edmcgs.geometry import Intrinsics
from edmcgs.poses import estimate_poses
from edmcgs.synth.build import scene_imu
from edmcgs.synth.davis import ImuConfig
from edmcgs.synth.scene import make_scene, render
from harness.pose_scenes import rigid_sweep, trajectory_error

REAL = Path(__file__).resolve().parents[1] / "tests" / "data" / "test-frame.aedat4"
SCENES = ("jumpingjack-sweep", "jumpingjack-orbit", "rigid-small", "rigid-60", "traffic-pan", "test-frame")
TARGETS = {"ate_pct": ("<=", 1.0), "ate_pct_max": ("<=", 1.0), "registered_pct": (">=", 95.0),
           "rigid-60_wall_s": ("<=", 120.0), "traffic-pan_wall_s": ("<=", 120.0)}


def synth_frames(name: str, camera: str, seconds: float, rate_hz: float = 25.0):
    """(t_us, uint8 frames, true c2w, intrinsics, IMU samples) of scene ``name`` at ``rate_hz``, small."""
    scene = make_scene(name, "small", camera)
    t_us = np.rint(np.arange(round(seconds * rate_hz) + 1) * 1e6 / rate_hz).astype(np.int64)
    c2w = np.stack([scene.camera_at(t * 1e-6) for t in t_us])
    images = np.stack([np.rint(render(scene, t * 1e-6) * 255).astype(np.uint8) for t in t_us])
    imu, _ = scene_imu(scene, int(t_us[-1]), ImuConfig(), seed=0)
    return t_us, images, c2w, scene.intrinsics, imu


def recording_frames(path: str):
    """(t_us, frames, true c2w or None, intrinsics or None, IMU samples or None) of a recording, every
    frame."""
    from edmcgs.pipeline import all_frames, open_recording

    rec = open_recording(path)
    frames = all_frames(rec)
    truth = frames.poses
    if truth is None and rec.trajectory_t_us is not None:
        from edmcgs.geometry import Trajectory

        truth = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w).at(frames.t_us)
    k = None if rec.intrinsics is None else Intrinsics(*(float(v) for v in rec.intrinsics), rec.width,
                                                       rec.height)
    return frames.t_us, frames.images, truth, k, rec.imu


def scene_frames(name: str, quick: bool):
    if name.startswith("jumpingjack-"):
        return synth_frames("jumpingjack", name.split("-")[1], 2.0 if quick else 4.0)
    if name == "rigid-small":
        return (*rigid_sweep(26, 12.5), None)
    if name == "rigid-60":
        return (*rigid_sweep(30 if quick else 60, 25.0, size="full"), None)
    if name == "traffic-pan":
        from edmcgs.synth.traffic import TrafficScene

        scene = TrafficScene(pan_px_s=12.0, seed=0)
        t_us = np.arange(30 if quick else 60, dtype=np.int64) * 40_000
        images = np.stack([np.rint(np.clip(scene.render(t * 1e-6), 0, 1) * 255).astype(np.uint8)
                           for t in t_us])
        return t_us, images, np.stack([scene.camera_at(t * 1e-6) for t in t_us]), None, None
    if name == "test-frame":
        t_us, images, _, _, imu = recording_frames(str(REAL))
        return t_us, images, None, None, imu
    return recording_frames(name)


def measure(name: str, quick: bool) -> dict:
    """One scene's row."""
    t_us, images, truth, intrinsics, imu = scene_frames(name, quick)
    row: dict = {"frames": len(t_us), "size": f"{images.shape[2]}x{images.shape[1]}", "imu": imu is not None}
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        estimate = estimate_poses(t_us, images, intrinsics, imu=imu, progress=False)
    except EdmcgsError as exc:
        row.update(error=str(exc), wall_s=time.perf_counter() - wall, cpu_s=time.process_time() - cpu)
        return row
    row.update(wall_s=time.perf_counter() - wall, cpu_s=time.process_time() - cpu,
               registered=estimate.registered, registered_pct=100.0 * estimate.registered / len(t_us),
               models=estimate.models, static=estimate.static, summary=estimate.summary())
    if truth is not None and not estimate.static:
        truth = truth[np.searchsorted(t_us, estimate.t_us)]
        row["rot_deg"] = max(_angle(a, b) for a, b in zip(_from_first(estimate.c2w), _from_first(truth),
                                                             strict=True))
        if not estimate.rotation_only:
            rmse, length = trajectory_error(estimate.t_us, estimate.c2w, truth)
            row.update(ate_m=rmse, path_m=length, ate_pct=100.0 * rmse / length)
        if estimate.frames_c2w is not None:  # the frames' own poses, before the IMU refined them
            frames = estimate.frames_c2w
            rmse, length = trajectory_error(estimate.t_us, frames, truth)
            row.update(frames_only_ate_pct=100.0 * rmse / length, frames_only_rot_deg=max(
                _angle(a, b) for a, b in zip(_from_first(frames), _from_first(truth), strict=True)))
    return row


def _median_run(runs: list[dict]) -> dict:
    """The run with the median trajectory error, with every run's error and the largest; the first run
    that failed, if any did (with how many); the first, for a scene with no truth."""
    failed = [run for run in runs if "error" in run]
    if failed:
        return failed[0] | {"failed_runs": len(failed), "runs": len(runs)}
    errors = [run.get("ate_pct") for run in runs]
    if len(runs) == 1 or any(e is None for e in errors):
        return runs[0]
    order = np.argsort(errors, kind="stable")
    return runs[int(order[(len(runs) - 1) // 2])] | {"ate_pct_runs": errors, "ate_pct_max": max(errors)}


def _from_first(c2w: np.ndarray) -> np.ndarray:
    """Rotations relative to the first frame's."""
    return np.swapaxes(c2w[:1, :3, :3], 1, 2) @ c2w[:, :3, :3]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1.0, 1.0))))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.poses", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--quick", action="store_true", help="shorter scenes (a smoke run)")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"of {', '.join(SCENES)} (default all)")
    parser.add_argument("--recording", action="append", default=[], metavar="REC",
                        help="also any recording (AEDAT4 or HDF5), scored against its true poses if it has "
                             "them")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="estimate each scene N times (COLMAP's threads make runs differ): the row of "
                             "the run with the median trajectory error, and every run's error (default 1)")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    names = [s for s in args.scenes.split(",") if s]
    unknown = sorted(set(names) - set(SCENES))
    if unknown:
        parser.error(f"unknown scenes {unknown}; choose among {', '.join(SCENES)}")
    names += args.recording
    rows: dict[str, dict] = {}
    with tqdm(names, desc="bench.poses", unit="scene") as bar:
        for name in bar:
            bar.set_postfix_str(Path(name).name)
            runs = [measure(name, args.quick) for _ in range(args.repeat)]
            rows[Path(name).stem if name in args.recording else name] = _median_run(runs)
    flat: dict = {"load_avg_1m": os.getloadavg()[0], "quick": args.quick}
    targets = {}
    for name, row in rows.items():
        for key, value in row.items():
            flat[f"{name}_{key}"] = value
            if key in TARGETS and (key != "registered_pct" or name == "test-frame"):
                targets[f"{name}_{key}"] = TARGETS[key]
        if f"{name}_wall_s" in TARGETS and "wall_s" in row:
            targets[f"{name}_wall_s"] = TARGETS[f"{name}_wall_s"]
    print()
    print(table(flat, targets))
    for name, row in rows.items():
        print(f"{name}: {row.get('summary') or row.get('error')}")
    write_json(args.json, {"scenes": rows, "load_avg_1m": flat["load_avg_1m"], "quick": args.quick})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
