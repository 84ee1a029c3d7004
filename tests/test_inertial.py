"""The IMU's refinement of structure from motion's poses (``edmcgs.inertial``, ``edmcgs.poses.with_imu``):
a handheld path, its IMU as a DAVIS346 reads it, and "frames" poses that follow the camera badly (as
structure from motion does when the scene itself moves)."""

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Similarity, nearest_rotation, rotation_exp, rotation_log
from edmcgs.inertial import ImuUnusable, fuse_imu
from edmcgs.poses import PoseEstimate, with_imu
from edmcgs.sensor.imu import IMU_DTYPE
from edmcgs.synth.davis import ImuConfig, simulated_imu
from edmcgs.synth.street3d import HandheldPath
from harness.pose_scenes import trajectory_error

SECONDS = 4.0


def _imu(c2w, seed: int = 0, stop_s: float = SECONDS) -> np.ndarray:
    """What the IMU reads along the path ``c2w(t_s [K]) -> [K, 4, 4]`` from 0 to ``stop_s``."""
    return simulated_imu(c2w, round(stop_s * 1e6), ImuConfig(), seed)[0]


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle of each frame's rotation relative to the first, a against b."""
    rel = [np.swapaxes(c[:1, :3, :3], 1, 2) @ c[:, :3, :3] for c in (a, b)]
    return np.degrees(np.linalg.norm(rotation_log(np.swapaxes(rel[0], 1, 2) @ rel[1]), axis=1))


@pytest.fixture(scope="module")
def scene():
    """(t_us, true c2w, frames' c2w, IMU): 25 Hz frames over 4 s of a handheld walk; the frames' poses in
    another world and scale (0.3 units per metre), each rotation off by 2 deg at random, each position
    off by 2 cm at random plus a 4 cm bob at 3.6 Hz (a figure's jumps). (A drift of the frames' rotation
    that grows steadily reads as the gyro's bias while the part could have that bias: beyond it,
    ``test_frames_that_drift_against_the_gyro_give_way_to_it``.)"""
    path = HandheldPath(1)
    t_us = np.arange(0, round(SECONDS * 1e6) + 1, 40_000, dtype=np.int64)
    truth = path.c2w(t_us * 1e-6)
    rng = np.random.default_rng(3)
    t = t_us * 1e-6
    frames = truth.copy()
    jitter = rng.normal(0, np.radians(2.0) / np.sqrt(3), (len(t), 3))
    frames[:, :3, :3] = truth[:, :3, :3] @ rotation_exp(jitter)
    frames[:, :3, 3] += rng.normal(0, 0.02 / np.sqrt(3), (len(t), 3))
    frames[:, 2, 3] += 0.04 * np.sin(2 * np.pi * 3.6 * t)
    world = np.eye(4)
    world[:3, :3] = rotation_exp(np.array([0.3, -1.0, 0.2]))
    world[:3, 3] = [1.0, 2.0, -0.5]
    frames = Similarity(0.3, world[:3, :3], world[:3, 3]).poses(frames)
    return t_us, truth, frames, _imu(path.c2w)


def test_the_imu_removes_what_the_frames_got_wrong(scene):
    t_us, truth, frames, imu = scene
    fit = fuse_imu(t_us, frames, imu)
    before, length = trajectory_error(t_us, frames, truth)
    after, _ = trajectory_error(t_us, fit.c2w, truth)
    assert after < 0.25 * before and after / length < 0.005, (before, after, length)
    assert _angles_deg(frames, truth).max() > 3.0
    assert _angles_deg(fit.c2w, truth).max() < 0.5
    assert fit.metres_per_unit == pytest.approx(1 / 0.3, rel=0.05)
    assert np.isfinite(fit.c2w).all() and fit.rotation_scatter_deg > 1.0
    assert "IMU fused" in fit.summary()


def test_exact_frames_stay_exact(scene):
    t_us, truth, _, imu = scene
    fit = fuse_imu(t_us, truth, imu)
    error, length = trajectory_error(t_us, fit.c2w, truth)
    assert error / length < 1e-3
    assert _angles_deg(fit.c2w, truth).max() < 0.05
    assert fit.metres_per_unit == pytest.approx(1.0, rel=0.01)
    np.testing.assert_allclose(fit.gravity, [0, 0, -1], atol=0.01)  # the world of HandheldPath: z up


def _turning(rate: float):
    """A path that turns about every axis (by up to 17 deg) while it moves: its IMU's mounting is
    observable."""
    def c2w(t_s):
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        w = np.stack([0.3 * np.sin(1.3 * rate * t), 0.25 * np.sin(0.9 * rate * t + 1),
                      0.2 * np.sin(1.7 * rate * t + 2)], -1)
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3] = rotation_exp(w)
        out[:, :3, 3] = np.stack([np.sin(t), 0.5 * np.sin(1.5 * t), 0.3 * t], -1)
        return out
    return c2w


def test_the_imus_mounting_is_estimated_and_another_cameras_imu_left_out():
    t_us = np.arange(0, round(SECONDS * 1e6) + 1, 40_000, dtype=np.int64)
    truth = _turning(1.0)(t_us * 1e-6)
    frames = truth.copy()
    jitter = np.random.default_rng(3).normal(0, np.radians(2.0) / np.sqrt(3), (len(t_us), 3))
    frames[:, :3, :3] = truth[:, :3, :3] @ rotation_exp(jitter)
    swapped = _imu(_turning(1.0))  # this camera's IMU, its axes in another order
    swapped["gyro"], swapped["accel"] = swapped["gyro"][:, [2, 0, 1]], swapped["accel"][:, [2, 0, 1]]
    fit = fuse_imu(t_us, frames, swapped)
    np.testing.assert_allclose(fit.imu_to_camera, np.eye(3)[[1, 2, 0]], atol=0.1)  # camera x = IMU y ...
    assert _angles_deg(fit.c2w, truth).max() < 0.3 * _angles_deg(frames, truth).max()
    with pytest.raises(ImuUnusable, match="gyro's rotations differ from the frames' by"):
        fuse_imu(t_us, frames, _imu(_turning(1.6), seed=1))  # another camera's motion


def test_an_imu_that_misses_the_span_or_has_a_gap_is_left_out(scene):
    t_us, _, frames, _ = scene
    with pytest.raises(ImuUnusable, match=r"covers 2\.0 of the 4\.0 s"):
        fuse_imu(t_us, frames, _imu(HandheldPath(1).c2w, stop_s=2.0))
    imu = _imu(HandheldPath(1).c2w)
    gap = (imu["t"] > 1_000_000) & (imu["t"] < 1_200_000)
    with pytest.raises(ImuUnusable, match=r"gap of 0\.20 s"):
        fuse_imu(t_us, frames, imu[~gap])
    with pytest.raises(ImuUnusable, match="0 IMU samples"):
        fuse_imu(t_us, frames, np.zeros(0, IMU_DTYPE))


def test_non_finite_samples_are_dropped_and_bad_input_named(scene):
    t_us, truth, _, imu = scene
    broken = imu.copy()
    broken["gyro"][500] = np.nan
    broken["accel"][800] = np.inf
    fit = fuse_imu(t_us, truth, broken)
    assert np.isfinite(fit.c2w).all()
    with pytest.raises(InvalidInputError, match="IMU samples"):
        fuse_imu(t_us, truth, np.zeros((10, 7)))
    with pytest.raises(InvalidInputError, match="strictly increasing"):
        fuse_imu(t_us[::-1], truth, imu)
    with pytest.raises(InvalidInputError, match="finite"):
        fuse_imu(t_us, truth * np.nan, imu)
    with pytest.raises(ImuUnusable, match="at least 3"):
        fuse_imu(t_us[:2], truth[:2], imu)


def test_with_imu_moves_the_world_to_the_first_refined_camera(scene):
    t_us, _, frames, imu = scene
    base = np.linalg.inv(frames[0])
    frames = base @ frames  # structure from motion's convention: the first frame's camera is the world
    points = np.random.default_rng(0).normal(0, 1, (50, 3)) + np.array([0.0, 0.0, 3.0])
    estimate = PoseEstimate(frames=len(t_us), registered=len(t_us), t_us=t_us, c2w=frames, intrinsics=None,
                            estimated_intrinsics=False, distortion=0.0, static=False, models=1, points=50,
                            motion_px=5.0, seconds=1.0, point_xyz=points)
    refined = with_imu(estimate, imu)
    np.testing.assert_allclose(refined.c2w[0], np.eye(4), atol=1e-9)
    assert refined.imu.startswith("IMU fused") and "IMU fused" in refined.summary()
    # the points moved with the poses: each seen from each camera as in the fit's own world
    fit = fuse_imu(t_us, frames, imu)
    camera = np.linalg.inv(fit.c2w[10]) @ np.c_[points, np.ones(50)].T
    moved = np.linalg.inv(refined.c2w[10]) @ np.c_[refined.point_xyz, np.ones(50)].T
    np.testing.assert_allclose(moved, camera, atol=1e-9)
    left_out = with_imu(estimate, imu[imu["t"] < 1_000_000])
    assert left_out.imu.startswith("IMU left out: the IMU covers")
    np.testing.assert_array_equal(left_out.c2w, frames)


def _orbit(t_s):
    """A camera circling a point 2.8 m away at 25 deg/s, level, looking at it (z up): the IMU's hard case,
    its centripetal pull a constant along the optical axis, as a bias would be."""
    t = np.atleast_1d(np.asarray(t_s, np.float64))
    angle = np.radians(25.0) * t
    out = np.tile(np.eye(4), (len(t), 1, 1))
    forward = -np.stack([np.cos(angle), np.sin(angle), np.zeros_like(t)], -1)
    right = np.stack([np.sin(angle), -np.cos(angle), np.zeros_like(t)], -1)
    down = np.cross(forward, right)
    out[:, :3, :3] = np.stack([right, down, forward], -1)
    out[:, :3, 3] = -2.8 * forward
    return out


def test_frames_that_drift_against_the_gyro_give_way_to_it():
    """Structure from motion that falls 6 deg/s behind the camera's turn (as on jumpingjack's orbit): the
    bias that would explain it is beyond the part's, so the gyro's rotations are kept; the positions the
    caller estimates again with them (``adjust``) are the ones fused."""
    t_us = np.arange(0, round(SECONDS * 1e6) + 1, 40_000, dtype=np.int64)
    truth = _orbit(t_us * 1e-6)
    rng = np.random.default_rng(5)
    frames = truth.copy()
    behind = np.outer(t_us * 1e-6, [0.0, np.radians(-6.0), 0.0])  # about the camera's vertical axis
    frames[:, :3, :3] = truth[:, :3, :3] @ rotation_exp(behind + rng.normal(0, np.radians(1.5), behind.shape))
    frames[:, :3, 3] += rng.normal(0, 0.05, (len(t_us), 3))  # the positions the drift pulled along
    to_units = Similarity(1 / 2.8, np.eye(3), np.zeros(3))  # the unit: the scene's median depth
    frames = to_units.poses(frames)
    positions = to_units.poses(truth)[:, :3, 3] + rng.normal(0, 0.01, (len(t_us), 3))
    held = []

    def adjust(rotations):
        """A bundle adjustment's answer: the true positions, in the world the rotations are given in."""
        held.append(rotations)
        world = nearest_rotation(np.einsum("nij,nkj->ik", rotations, truth[:, :3, :3]))
        return positions @ world.T

    fit = fuse_imu(t_us, frames, _imu(_orbit), adjust=adjust)
    assert fit.frames_drift_dps is not None and fit.frames_drift_dps > 3.0
    assert "the frames' rotations drift" in fit.summary()
    assert len(held) == 1 and held[0].shape == (len(t_us), 3, 3)
    assert _angles_deg(frames, truth).max() > 20.0
    # the frames barely speak of the bias: it is the prior's, the true one's turn (0.9 deg/s) left in
    assert _angles_deg(fit.c2w, truth).max() < 4.0
    assert np.linalg.norm(fit.gyro_bias_dps) < 2.0
    error, length = trajectory_error(t_us, fit.c2w, truth)
    assert error / length < 0.01, (error, length)


def test_frames_that_bend_once_give_way_to_the_gyro():
    """Structure from motion exact to a few hundredths of a degree that bends by 4 deg over half a second (a
    close car pulled its map round, as on street3d at 30 s) and holds the bend: a bias that explains it is
    one the part could have, but not one the frames' own steps allow, so the gyro's rotations are kept."""
    path = HandheldPath(1)
    t_us = np.arange(0, round(SECONDS * 1e6) + 1, 40_000, dtype=np.int64)
    t = t_us * 1e-6
    truth = path.c2w(t)
    rng = np.random.default_rng(7)
    bend = np.outer(np.clip((t - 2.0) / 0.5, 0.0, 1.0), [0.0, np.radians(4.0), 0.0])
    frames = truth.copy()
    frames[:, :3, :3] = truth[:, :3, :3] @ rotation_exp(bend + rng.normal(0, np.radians(0.02), bend.shape))
    fit = fuse_imu(t_us, frames, _imu(path.c2w), adjust=lambda rotations: truth[:, :3, 3])
    assert fit.frames_drift_dps is not None
    assert _angles_deg(frames, truth).max() > 3.5
    assert _angles_deg(fit.c2w, truth).max() < 1.0, _angles_deg(fit.c2w, truth).max()
