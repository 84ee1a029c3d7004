"""Frames with true camera poses for structure from motion: what the pose tests and ``bench.poses`` share.

``rigid_sweep``: the ``lego`` scene held at one instant (a rigid object with depth, on a studded plate),
seen along its camera's arc, so every pose is known and nothing in view moves but the camera.
``trajectory_error``: absolute trajectory error after a Sim(3) alignment, computed by ``evo``.
"""

from __future__ import annotations

import numpy as np

from edmcgs.geometry import Intrinsics
from edmcgs.synth.scene import make_scene, render


def rigid_sweep(frames: int = 26, rate_hz: float = 12.5, *, size: str = "small", instant_s: float = 0.3,
                moving: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, Intrinsics]:
    """(t_us int64 [F], uint8 [F, H, W, 3], true c2w [F, 4, 4], intrinsics) of ``lego`` frozen at
    ``instant_s``, the camera on its arc (``moving=False``: held at the arc's start)."""
    scene = make_scene("lego", size, "sweep")
    t_us = np.rint(np.arange(frames) * 1e6 / rate_hz).astype(np.int64)
    c2w = np.stack([scene.camera_at(t * 1e-6 if moving else 0.0) for t in t_us])
    images = np.stack([np.rint(render(scene, instant_s, pose) * 255).astype(np.uint8) for pose in c2w])
    return t_us, images, c2w, scene.intrinsics


def trajectory_error(t_us: np.ndarray, estimated: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(RMSE of the positions after aligning ``estimated`` to ``truth`` by a similarity (evo's Umeyama
    alignment with scale), the true path length), in the truth's units; both [F, 4, 4] c2w at ``t_us``."""
    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    seconds = np.asarray(t_us, dtype=np.float64) * 1e-6
    est = PoseTrajectory3D(poses_se3=list(estimated), timestamps=seconds)
    ref = PoseTrajectory3D(poses_se3=list(truth), timestamps=seconds)
    est.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse)), float(ref.path_length)
