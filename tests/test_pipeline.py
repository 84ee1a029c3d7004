"""Any recording in, no code: the anchor split, intrinsics, poses and formats of ``edmcgs.pipeline``, the
baselines every score stands beside, and train / eval on an AEDAT4 written by dv-processing."""

import csv

import numpy as np
import pytest

from edmcgs.cli import main
from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.model.eval.baselines import BASELINES, baseline_image, score_baselines
from edmcgs.model.eval.compare import Comparison
from edmcgs.model.eval.evaluation import FrameScore
from edmcgs.pipeline import (
    RecordingOptions,
    estimated_poses,
    open_recording,
    read_tum,
    split_at,
    split_frames,
    training_data,
    with_trajectory,
)
from edmcgs.sensor.files.recording import Recording, write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.esim import simulate_frames
from tests.support import tiny_scene
from tests.support.recordings import write_aedat

FRAME_US = 8_000  # a 125 Hz APS camera over the tiny scene's 200 ms
TINY = ["init_points=400", "num_control_points=16", "deform_width=32", "deform_depth=2", "iterations=4",
        "substeps=4", "max_pair_steps=4", "eval_every=0", "checkpoint_every=0"]


def _frames(t_us, channels=1):
    return np.stack([tiny_scene.to_uint8(tiny_scene.image(int(t), channels=channels)) for t in t_us])


@pytest.fixture(scope="module")
def aps(tmp_path_factory):
    """(AEDAT4 path, frame times): every frame of a DAVIS-like camera, events from the simulator."""
    t = tiny_scene.T0 + np.arange(0, 200_001, FRAME_US, dtype=np.int64)
    fine = tiny_scene.T0 + np.arange(0, 200_001, 1_000, dtype=np.int64)
    events = simulate_frames(fine, np.stack([tiny_scene.image(int(ti)) for ti in fine]))
    path = tmp_path_factory.mktemp("aps") / "square.aedat4"
    return write_aedat(path, events, Frames(t, _frames(t)), tiny_scene.W, tiny_scene.H), t


def _recording(n=26, held=()):
    t = tiny_scene.T0 + FRAME_US * np.arange(n, dtype=np.int64)
    frames = Frames(t, _frames(t))
    held_frames = None
    if held:
        h = tiny_scene.T0 + np.asarray(held, dtype=np.int64)
        held_frames = Frames(h, _frames(h))
    events = simulate_frames(t, frames.images / 255.0)
    return Recording(width=tiny_scene.W, height=tiny_scene.H, events=events, anchors=frames,
                     held_out=held_frames)


def test_anchor_split_by_count_or_rate_keeps_every_other_frame_held_out():
    rec = _recording(26)
    every = split_frames(rec, every=5)
    assert every.anchors.t_us.tolist() == rec.anchors.t_us[::5].tolist()
    assert len(every.held_out) == 26 - 6 and not np.isin(every.held_out.t_us, every.anchors.t_us).any()
    by_rate = split_frames(rec, fps=1e6 / (5 * FRAME_US))  # the same ticks as every 5th
    assert by_rate.anchors == every.anchors and by_rate.held_out == every.held_out
    again = split_at(every, every.anchors.t_us)  # a checkpoint's anchor times give the split back
    assert again.anchors == every.anchors and again.held_out == every.held_out
    jittered = split_frames(rec, fps=1e6 / (5 * FRAME_US + 100))  # ticks drift: the nearest frame each
    assert len(jittered.anchors) in (5, 6) and jittered.anchors.t_us[0] == rec.anchors.t_us[0]
    with pytest.raises(InvalidInputError, match="no frames at 1 of the anchor times"):
        split_at(rec, [int(rec.anchors.t_us[0]) + 1])
    with pytest.raises(InvalidInputError, match="anchor-every"):
        split_frames(rec, every=0)
    with pytest.raises(InvalidInputError, match="anchor-fps"):
        split_frames(rec, fps=float("nan"))


def test_a_split_merges_stored_held_out_frames_in_time_order():
    rec = _recording(6, held=(4_000, 12_000))
    split = split_frames(rec, every=2)
    everything = np.sort(np.concatenate([rec.anchors.t_us, rec.held_out.t_us]))
    assert split.anchors.t_us.tolist() == everything[::2].tolist()
    assert sorted([*split.anchors.t_us, *split.held_out.t_us]) == everything.tolist()


def test_baselines_hold_and_blend_the_neighbouring_anchors():
    data = training_data(split_frames(_recording(11), every=5))
    a0, a1 = data.anchors_t_us[:2]
    img0, img1 = (data.anchor_images[i].astype(np.float32) / 255 for i in (0, 1))
    hold, tau = baseline_image(data, int(a0) + 3 * FRAME_US, BASELINES[0])
    assert tau == a0 and np.array_equal(hold, img0)
    mid, _ = baseline_image(data, int((a0 + a1) // 2), BASELINES[1])
    np.testing.assert_allclose(mid, 0.5 * (img0 + img1), atol=1e-6)
    last, tau = baseline_image(data, int(data.anchors_t_us[-1]) + 1, BASELINES[1])
    assert tau == data.anchors_t_us[-1] and np.array_equal(last, data.anchor_images[-1] / np.float32(255))
    scores = score_baselines(data)
    assert set(scores) == set(BASELINES) and all(len(v) == 8 for v in scores.values())
    assert np.mean([r.psnr for r in scores[BASELINES[1]]]) > np.mean([r.psnr for r in scores[BASELINES[0]]])


def test_a_comparison_names_the_baselines_a_method_loses_to():
    def rows(psnr):
        return [FrameScore(i, 1000 * i, 0, 0, p, 0.5) for i, p in enumerate(psnr)]

    comparison = Comparison({"model": rows([20, 22]), "hold": rows([25, 25]), "blend": rows([19, 20])})
    assert comparison.losses("model", ("hold", "blend")) == ["model loses to hold by 4.00 dB PSNR"]
    assert "| model | 21.00 |" in comparison.markdown()
    with pytest.raises(ValueError, match="same frames"):
        Comparison({"model": rows([1, 2]), "hold": rows([1])})


def test_train_and_eval_an_aedat4_with_a_split(aps, tmp_path, capsys):
    path, t = aps
    ckpt = tmp_path / "square.ckpt"
    intrinsics = f"40,40,{(tiny_scene.W - 1) / 2},{(tiny_scene.H - 1) / 2}"
    args = ["train", str(path), "-o", str(ckpt), "--anchor-every", "5", "--intrinsics", intrinsics, "--quiet"]
    assert main(args + [a for s in TINY for a in ("--set", s)]) == 0
    out = capsys.readouterr().out
    assert "a static camera" in out and "hold last anchor:" in out and "blend of neighbouring anchors:" in out
    out_csv = tmp_path / "eval.csv"
    assert main(["eval", str(ckpt), str(path), "--csv", str(out_csv)]) == 0  # the checkpoint's own split
    rows = list(csv.DictReader(out_csv.open()))
    assert len(rows) == len(t) - len(t[::5]) and {int(r["t_us"]) for r in rows} == set(t) - set(t[::5])
    # its baselines are the ones the trainer's last line scored, on the same frames
    data = training_data(split_frames(open_recording(path), every=5))
    hold = score_baselines(data)[BASELINES[0]]
    assert [float(r["psnr_hold_last"]) for r in rows] == pytest.approx([h.psnr for h in hold], abs=1e-4)
    integrated = score_baselines(data)[BASELINES[2]]
    assert [float(r["psnr_integrate"]) for r in rows] == pytest.approx([h.psnr for h in integrated], abs=1e-4)
    printed = capsys.readouterr().out
    assert "| hold last anchor |" in printed and "| blend of neighbouring anchors |" in printed


def test_intrinsics_given_or_from_a_dv_calibration_and_distortion_refused(tmp_path):
    import dv_processing as dv

    rec_path = write_recording(tmp_path / "r.h5", _recording(4))
    got = open_recording(rec_path, RecordingOptions(intrinsics="41,42,23.5,15.5")).intrinsics
    assert got.tolist() == [41, 42, 23.5, 15.5]
    with pytest.raises(InvalidInputError, match="fx,fy,cx,cy"):
        open_recording(rec_path, RecordingOptions(intrinsics="41,42,23.5"))

    def calibration(name, distortion):
        cam = dv.camera.calibrations.CameraCalibration(
            "C0", "left", True, (tiny_scene.W, tiny_scene.H), (23.5, 15.5), (40.0, 41.0), distortion,
            dv.camera.DistortionModel.RADIAL_TANGENTIAL, dv.kinematics.Transformationf(), None)
        calibrations = dv.camera.CalibrationSet()
        calibrations.addCameraCalibration(cam)
        calibrations.writeToFile(str(tmp_path / name))
        return str(tmp_path / name)

    sharp = calibration("sharp.json", [0.0, 0.0, 0.0, 0.0, 0.0])
    got = open_recording(rec_path, RecordingOptions(intrinsics=sharp)).intrinsics
    assert got.tolist() == [40, 41, 23.5, 15.5]
    barrel = calibration("barrel.json", [-0.3, 0.1, 0.0, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match=r"lens distortion .* moves pixels by up to"):
        open_recording(rec_path, RecordingOptions(intrinsics=barrel))


def test_tum_poses_become_the_trajectory(tmp_path):
    rec_path = write_recording(tmp_path / "r.h5", _recording(4))
    t0 = tiny_scene.T0 / 1e6
    traj = tmp_path / "traj.txt"
    traj.write_text(f"# t tx ty tz qx qy qz qw\n{t0:.6f} 0 0 0 0 0 0 1\n"
                    f"{t0 + 0.05:.6f} 1 0 0 0 0.7071068 0 0.7071068\n")
    t_us, c2w = read_tum(traj)
    assert t_us.tolist() == [tiny_scene.T0, tiny_scene.T0 + 50_000]
    np.testing.assert_allclose(c2w[1, :3, :3], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-6)  # 90° about y
    rec = open_recording(rec_path, RecordingOptions(poses=str(traj)))
    assert rec.trajectory_t_us.tolist() == t_us.tolist() and rec.anchors.poses is None
    traj.write_text(f"{t0} 0 0 0 0 0 0\n")
    with pytest.raises(InvalidInputError, match=r"traj.txt:1: expected 8 numbers"):
        read_tum(traj)
    traj.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    with pytest.raises(InvalidInputError, match="miss the recording's"):
        open_recording(rec_path, RecordingOptions(poses=str(traj)))


def test_unreadable_formats_name_what_was_found_and_what_is_read(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ReplayFormatError, match=r"notes.txt is not a recording read here .*AEDAT4.*AEDAT "
                       r"2\.0 / 3\.1.*Prophesee RAW.*DSEC.*ROS 1 bag.*RPG text layout"):
        open_recording(tmp_path / "notes.txt")
    with pytest.raises(ReplayFormatError, match="no such file"):
        open_recording(tmp_path / "missing.aedat4")


def test_record_stores_the_split_for_train_and_eval(aps, tmp_path, capsys):
    path, t = aps
    out = tmp_path / "split.h5"
    fps = str(1e6 / (5 * FRAME_US))
    assert main(["record", str(path), "-o", str(out), "--anchor-fps", fps, "--quiet"]) == 0
    assert f"{len(t[::5])} anchors, {len(t) - len(t[::5])} held-out frames" in capsys.readouterr().out
    rec = open_recording(out)
    assert rec.anchors.t_us.tolist() == t[::5].tolist() and len(rec.held_out) == len(t) - len(t[::5])
    with pytest.raises(SystemExit):
        main(["record", str(path), "-o", str(tmp_path / "x.aedat4"), "--anchor-every", "5"])
    assert "our HDF5 format" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["train", "eval", "export-ply"])
def test_help_is_instant_no_torch_before_the_arguments_parse(command):
    import subprocess
    import sys

    code = (f"import sys\nfrom edmcgs.cli import main\ntry:\n    main([{command!r}, '--help'])\n"
            "except SystemExit:\n    pass\nassert 'torch' not in sys.modules, 'torch imported for --help'")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "usage: edmcgs" in done.stdout


def test_record_with_a_split_honours_start_and_duration_and_refuses_what_it_cannot(aps, tmp_path, capsys):
    path, t = aps
    out = tmp_path / "cut.h5"
    args = ["record", str(path), "-o", str(out), "--anchor-every", "2", "--quiet"]
    assert main([*args, "--start", "0.05", "--duration", "0.1"]) == 0
    whole = open_recording(path)
    begin = whole.t_range_us[0] + 50_000
    first = whole.events.time_slice(begin, 2**62).t_start
    rec = open_recording(out)
    assert rec.events == whole.events.time_slice(begin, first + 100_000)
    kept = t[(t >= begin) & (t < first + 100_000)]
    assert rec.anchors.t_us.tolist() == kept[::2].tolist()
    assert rec.held_out.t_us.tolist() == kept[1::2].tolist()
    assert "events" in capsys.readouterr().out
    for flag, said in ((["--factor", "1"], "--factor"), (["--no-frames"], "--no-frames")):
        with pytest.raises(SystemExit):
            main([*args, "--force", *flag])
        assert said in capsys.readouterr().err
    events_only = tmp_path / "events_only.h5"
    assert main(["record", str(path), "-o", str(events_only), "--intrinsics", "40,40,23.5,15.5",
                 "--no-frames", "--quiet"]) == 0
    rec = open_recording(events_only)
    assert len(rec.anchors) == 0 and rec.held_out is None and len(rec.events) == len(whole.events)
    assert rec.intrinsics.tolist() == [40, 40, 23.5, 15.5]


def test_estimated_poses_bring_their_points_and_carry_the_novel_views_into_their_frame(monkeypatch):
    from edmcgs import poses
    from edmcgs.geometry import Similarity, pose_from_quat, project, world_to_camera

    rec = _recording(6)
    truth = np.stack([pose_from_quat([0.1 * i, 0.02 * i, 0.0], [1.0, 0.0, 0.01 * i, 0.0]) for i in range(6)])
    rig = pose_from_quat([-0.3, 0.0, 0.0], [1.0, 0.0, 0.04, 0.0])
    novel = Frames(rec.anchors.t_us[1:4] + 1, rec.anchors.images[1:4], truth[1:4] @ rig)
    rec = Recording(**{**rec.__dict__, "anchors": Frames(rec.anchors.t_us, rec.anchors.images, truth),
                       "novel_views": novel})
    to_estimate = Similarity(0.4, truth[5, :3, :3], np.array([0.3, -1.0, 2.0]))
    points = np.array([[0.0, 0.0, 3.0], [0.5, -0.2, 4.0], [-0.4, 0.3, 5.0], [0.2, 0.2, 2.0]])

    def estimate(t_us, images, intrinsics, imu, progress, threads):
        return poses.PoseEstimate(
            frames=len(t_us), registered=len(t_us), t_us=t_us, c2w=to_estimate.poses(truth), intrinsics=None,
            estimated_intrinsics=False, distortion=0.0, static=False, models=1, points=4, motion_px=5.0,
            seconds=0.1, point_xyz=to_estimate.points(points),
            point_colors=np.arange(4, dtype=np.uint8)[:, None])

    monkeypatch.setattr(poses, "estimate_poses", estimate)
    out = estimated_poses(rec)
    np.testing.assert_allclose(out.points_xyz, to_estimate.points(points))
    assert out.anchors.poses is None and len(out.trajectory_t_us) == 6
    data = training_data(out)  # the points come with the poses into the training data
    np.testing.assert_array_equal(data.points_xyz, out.points_xyz)
    # a novel view sees a point where it saw it before: the view moved into the estimated frame
    intr = tiny_scene.INTRINSICS
    k = 1
    uv_before, _ = project(points, world_to_camera(novel.poses[k]), intr)
    uv_after, _ = project(out.points_xyz, world_to_camera(out.novel_views.poses[k]), intr)
    np.testing.assert_allclose(uv_after, uv_before, atol=1e-6)
    # another trajectory is another world frame: the points go
    assert with_trajectory(out, out.trajectory_t_us, out.trajectory_c2w).points_xyz is None
    # without former poses the novel views cannot be related to the estimated ones: left out
    bare = Recording(**{**rec.__dict__, "anchors": Frames(rec.anchors.t_us, rec.anchors.images)})
    assert estimated_poses(bare).novel_views is None
