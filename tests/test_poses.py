"""Poses from a recording's own frames (``edmcgs.poses``, ``--poses auto``, ``edmcgs poses``): a real
handheld DAVIS346 recording, a synthetic moving camera scored against its true poses, a static camera,
a refusal, and the commands end to end."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from edmcgs import cli, poses
from edmcgs.errors import InvalidInputError, PoseEstimationError
from edmcgs.geometry import project, world_to_camera
from edmcgs.options import RecordingOptions
from edmcgs.pipeline import open_recording, read_tum, training_data, write_tum
from edmcgs.poses import estimate_poses
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording, read_recording, write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.build import scene_imu
from edmcgs.synth.davis import ImuConfig
from edmcgs.synth.scene import make_scene
from edmcgs.synth.traffic import TrafficScene
from harness.pose_scenes import rigid_sweep, trajectory_error

REAL = Path(__file__).parent / "data" / "test-frame.aedat4"


@pytest.fixture(scope="module")
def sweep():
    """26 frames of a rigid scene along a 36-degree arc, with their true poses."""
    return rigid_sweep(26, 12.5)


@pytest.fixture(scope="module")
def real_auto():
    """The real handheld recording, read with ``--poses auto``."""
    return open_recording(REAL, RecordingOptions(poses="auto"))


def _recording(t_us, images, intrinsics=None) -> Recording:
    h, w = images.shape[1:3]
    k = None if intrinsics is None else [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy]
    return Recording(width=w, height=h, events=Events.empty(), anchors=Frames(t_us, images), intrinsics=k)


def test_a_real_handheld_recording_registers_in_one_model(real_auto):
    poses = real_auto.metadata["poses"]
    assert poses["frames"] == 20 and not poses["static"]
    assert poses["registered"] >= 19  # >= 95 % in the one model kept
    assert len(real_auto.trajectory_t_us) == poses["registered"]
    assert np.allclose(real_auto.trajectory_c2w[0], np.eye(4))  # the world: the first frame's camera
    fx, fy, cx, cy = real_auto.intrinsics  # estimated (the file has no calibration) and stored
    assert poses["estimated_intrinsics"] and fx == fy and 150 < fx < 450
    assert abs(cx - 172.5) < 1 and abs(cy - 129.5) < 1
    # the camera tilts over the banner: it turns by degrees, not by nothing
    turn = np.degrees(np.arccos(np.clip((np.trace(real_auto.trajectory_c2w[-1][:3, :3]) - 1) / 2, -1, 1)))
    assert turn > 5
    data = training_data(real_auto)  # what train gets: a moving camera through every frame
    assert not data.trajectory.is_static and data.intrinsics.fx == fx


def test_a_synthetic_moving_camera_is_within_one_percent_of_its_path(sweep):
    t_us, images, truth, intrinsics = sweep
    estimate = estimate_poses(t_us, images, intrinsics, progress=False)
    assert estimate.registered == len(t_us) and not estimate.static
    assert not estimate.estimated_intrinsics and estimate.intrinsics == intrinsics
    rmse, length = trajectory_error(estimate.t_us, estimate.c2w, truth[np.searchsorted(t_us, estimate.t_us)])
    assert length > 1.0
    assert rmse <= 0.01 * length, f"ATE {rmse:.4f} of a {length:.3f} path"
    assert estimate.imu is None and estimate.frames_c2w is None
    _assert_points_show_in_frames(estimate, t_us, images, intrinsics)


def test_a_long_run_maps_keyframes_and_localizes_every_other_frame_against_them(monkeypatch):
    """Past twice ``MIN_KEYFRAMES`` frames the mapper sees only keyframes; every frame still registers,
    as accurately, with the points its own tracks add (the bound lowered: 72 frames stand for 200)."""
    monkeypatch.setattr(poses, "MIN_KEYFRAMES", 30)
    t_us, images, truth, intrinsics = rigid_sweep(72, 25.0)
    estimate = estimate_poses(t_us, images, intrinsics, progress=False)
    assert 30 <= estimate.keyframes < len(t_us)
    assert estimate.registered == len(t_us) == len(estimate.t_us)
    assert f"({estimate.keyframes} keyframes mapped)" in estimate.summary()
    rmse, length = trajectory_error(estimate.t_us, estimate.c2w, truth)
    assert rmse <= 0.01 * length, f"ATE {rmse:.4f} of a {length:.3f} path"
    _assert_points_show_in_frames(estimate, t_us, images, intrinsics)


def _assert_points_show_in_frames(estimate, t_us, images, intrinsics) -> None:
    """The points come in the poses' frame, in the colours the frames show where they project."""
    xyz, colors = estimate.point_xyz, estimate.point_colors
    assert xyz.shape == (estimate.points, 3) and estimate.points > 100 and colors.shape == (len(xyz), 3)
    for pose, image in zip(estimate.c2w[::6], images[np.searchsorted(t_us, estimate.t_us)][::6], strict=True):
        uv, z = project(xyz, world_to_camera(pose), intrinsics)
        u, v = np.rint(uv).astype(int).T
        seen = (z > 0) & (u >= 0) & (u < images.shape[2]) & (v >= 0) & (v < images.shape[1])
        assert seen.mean() > 0.8
        shown = image[v[seen], u[seen]].astype(int)
        assert np.median(np.abs(shown - colors[seen]).max(1)) <= 12


def test_with_the_cameras_imu_the_positions_follow_the_gyros_rotations(sweep):
    """The IMU a DAVIS346 reads on the sweep's arc: the rotations become the gyro's, the frames' positions
    and the points are adjusted again with them held, and the points still sit where the frames show them."""
    t_us, images, truth, intrinsics = sweep
    imu, _ = scene_imu(make_scene("lego", "small", "sweep"), int(t_us[-1]), ImuConfig(), seed=0)
    estimate = estimate_poses(t_us, images, intrinsics, imu=imu, progress=False)
    assert estimate.imu.startswith("IMU fused") and estimate.frames_c2w.shape == estimate.c2w.shape
    assert np.allclose(estimate.c2w[0], np.eye(4))
    rmse, length = trajectory_error(estimate.t_us, estimate.c2w, truth[np.searchsorted(t_us, estimate.t_us)])
    assert rmse <= 0.01 * length, f"ATE {rmse:.4f} of a {length:.3f} path"
    _assert_points_show_in_frames(estimate, t_us, images, intrinsics)


def test_the_scale_puts_the_scene_at_a_median_depth_of_one(sweep):
    t_us, images, truth, intrinsics = sweep
    estimate = estimate_poses(t_us[::2], images[::2], intrinsics, progress=False)
    means = make_scene("lego", "small").gaussians_at(0.3).means.astype(np.float64)
    depth = np.median([project(means, world_to_camera(pose), intrinsics)[1] for pose in truth[::2]])
    path = np.linalg.norm(np.diff(estimate.c2w[:, :3, 3], axis=0), axis=1).sum()
    true_path = np.linalg.norm(np.diff(truth[::2][:, :3, 3], axis=0), axis=1).sum()
    assert path == pytest.approx(true_path / depth, rel=0.3)  # the unit: the scene's median depth


def test_a_static_camera_is_detected_and_becomes_a_static_trajectory(tmp_path, capsys):
    t_us, images, _, intrinsics = rigid_sweep(8, 12.5, moving=False)
    noisy = np.clip(images + np.random.default_rng(0).normal(0, 2, images.shape), 0, 255).astype(np.uint8)
    estimate = estimate_poses(t_us, noisy, intrinsics, progress=False)
    assert estimate.static and estimate.motion_px < 1.0
    path = tmp_path / "still.h5"
    write_recording(path, _recording(t_us, noisy, intrinsics))
    rec = open_recording(path, RecordingOptions(poses="auto"))
    out = capsys.readouterr().out
    assert out.count("a static camera") == 1
    assert len(rec.trajectory_t_us) == 1 and np.array_equal(rec.trajectory_c2w[0], np.eye(4))
    assert training_data(rec).trajectory.is_static


def _street(pan_px_s: float, frames: int = 16):
    """The ``traffic`` street (cars crossing) at 173x130, 25 Hz: (t_us, frames, true c2w, camera)."""
    scene = TrafficScene(173, 130, pan_px_s=pan_px_s, seed=0)
    t_us = np.arange(frames, dtype=np.int64) * 40_000
    images = np.stack([np.rint(np.clip(scene.render(t * 1e-6), 0, 1) * 255).astype(np.uint8) for t in t_us])
    return t_us, images, np.stack([scene.camera_at(t * 1e-6) for t in t_us]), scene.intrinsics


def test_a_still_camera_over_moving_cars_is_static():
    t_us, images, _, _ = _street(0.0, frames=8)
    estimate = estimate_poses(t_us, images, None, progress=False)
    assert estimate.static and estimate.intrinsics is None  # nothing to estimate a camera from
    assert "a static camera" in estimate.summary()


def test_a_camera_that_only_turns_gets_rotations_from_homographies():
    t_us, images, truth, intrinsics = _street(150.0)  # 150 px/s at fx = 300: about 29 degrees a second
    estimate = estimate_poses(t_us, images, None, progress=False)
    assert estimate.rotation_only and estimate.registered == len(t_us)
    assert estimate.estimated_intrinsics and estimate.intrinsics.fx == pytest.approx(intrinsics.fx, rel=0.1)
    assert np.abs(estimate.c2w[:, :3, 3]).max() == 0  # no translation: no parallax to measure one
    angle = [np.degrees(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1)))
             for a, b in zip(estimate.c2w, truth[np.searchsorted(t_us, estimate.t_us)], strict=True)]
    turned = np.degrees(np.arccos((np.trace(truth[-1][:3, :3]) - 1) / 2))
    assert turned > 5 and max(angle) < 0.05 * turned
    given = estimate_poses(t_us, images, intrinsics, progress=False)
    assert given.rotation_only and given.intrinsics == intrinsics


def test_too_few_registered_frames_are_refused_with_the_count(sweep):
    t_us, images, _, intrinsics = sweep
    noise = np.random.default_rng(1).integers(0, 256, (10, *images.shape[1:]), dtype=np.uint8)
    mixed = np.concatenate([images[:12], noise])  # 12 frames of the scene, 10 of noise
    with pytest.raises(PoseEstimationError, match=r"only 1[0-2] of 22 frames registered in one model"):
        estimate_poses(t_us[:22], mixed, intrinsics, progress=False)
    with pytest.raises(PoseEstimationError, match=r"0 of 3|no two of the 3 frames match"):
        estimate_poses(t_us[:3], noise[:3], intrinsics, progress=False)
    with pytest.raises(PoseEstimationError, match="at least 3 frames"):
        estimate_poses(t_us[:2], images[:2], intrinsics, progress=False)
    with pytest.raises(InvalidInputError, match="strictly increasing"):
        estimate_poses(t_us[::-1], images, intrinsics, progress=False)


def test_tum_files_round_trip_to_the_microsecond(tmp_path):
    t_us = np.array([-1_500_000, 7, 1_632_919_370_314_775], dtype=np.int64)
    angles = [0.0, 0.3, -2.0]
    c2w = np.tile(np.eye(4), (3, 1, 1))
    for pose, a in zip(c2w, angles, strict=True):
        pose[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        pose[:3, 3] = [a, 2 * a, -a]
    write_tum(tmp_path / "t.txt", t_us, c2w)
    t_back, c2w_back = read_tum(tmp_path / "t.txt")
    assert np.array_equal(t_back, t_us)
    assert np.allclose(c2w_back, c2w, atol=1e-8)


def test_the_commands_end_to_end(sweep, tmp_path, capsys):
    t_us, images, truth, intrinsics = sweep
    path = tmp_path / "sweep.h5"
    write_recording(path, _recording(t_us[:14], images[:14]))  # no camera: it is estimated
    traj = tmp_path / "sweep.txt"
    assert cli.main(["poses", str(path), "-o", str(traj), "-q"]) == 0
    out = capsys.readouterr().out
    assert "14 of 14 frames registered" in out and "estimated camera" in out and "for --intrinsics:" in out
    t_back, c2w = read_tum(traj)
    assert np.array_equal(t_back, t_us[:14]) and np.allclose(c2w[0], np.eye(4))
    with pytest.raises(SystemExit, match="2"):  # it exists: --force replaces it
        cli.main(["poses", str(path), "-o", str(traj), "-q"])
    assert "exists (use --force" in capsys.readouterr().err

    stored = tmp_path / "sweep_posed.h5"  # record --poses auto stores the trajectory and the camera
    assert cli.main(["record", str(path), "-o", str(stored), "--poses", "auto", "--anchor-every", "4",
                     "--intrinsics", f"{intrinsics.fx},{intrinsics.fy},{intrinsics.cx},{intrinsics.cy}",
                     "-q"]) == 0
    assert "14 of 14 frames registered" in capsys.readouterr().out
    rec = read_recording(stored)
    assert len(rec.trajectory_t_us) == 14 and len(rec.anchors) == 4
    assert rec.metadata["poses"]["registered"] == 14 and not rec.metadata["poses"]["estimated_intrinsics"]
    rmse, length = trajectory_error(rec.trajectory_t_us, rec.trajectory_c2w, truth[:14])
    assert rmse <= 0.02 * length
    assert len(rec.points_xyz) > 100 and rec.points_colors.shape == (len(rec.points_xyz), 3)  # and its points

    noise = tmp_path / "noise.h5"
    rng = np.random.default_rng(2)
    write_recording(noise, _recording(t_us[:4], rng.integers(0, 256, (4, *images.shape[1:]), dtype=np.uint8)))
    assert cli.main(["poses", str(noise), "-o", str(tmp_path / "n.txt"), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("edmcgs poses: ") and "\n" not in err and "4 frames" in err
    assert not (tmp_path / "n.txt").exists()


def test_a_frames_only_aedat4_file_reads_as_a_recording(tmp_path):
    copy = tmp_path / "frames.aedat4"
    shutil.copy(REAL, copy)
    rec = open_recording(copy)
    assert (rec.width, rec.height, len(rec.events), len(rec.anchors)) == (346, 260, 0, 20)
    assert np.all(np.diff(rec.anchors.t_us) > 0)
