"""The dataset builder: a short recording, through the HDF5 file and back."""

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.sensor.files.recording import read_recording
from edmcgs.synth.build import BuildConfig, build_recording, frame_times, main
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig
from edmcgs.synth.scene import make_scene, render

# uniform 10 ms steps keep the tests quick; the real builds refine down to 250 µs
COARSE = AdaptiveSampling(dt_max_us=10_000, dt_min_us=10_000)


def _config(**kw):
    base = dict(scene="jumpingjack", fps=10.0, duration_s=0.3, held_out_per_interval=2, sampling=COARSE)
    return BuildConfig(**(base | kw))


@pytest.fixture(scope="module")
def recording():
    return build_recording(_config(), progress=False)


def test_frame_times_put_held_out_frames_between_anchors():
    anchors, held = frame_times(2.0, 5.0, 4)
    assert list(anchors) == [k * 200_000 for k in range(11)]
    assert len(held) == 40 and held[0] == 40_000 and held[3] == 160_000 and held[4] == 240_000
    assert len(frame_times(2.0, 10.0, 4)[0]) == 21
    with pytest.raises(InvalidInputError, match="fewer than 2 anchors"):
        frame_times(0.1, 5.0, 4)


def test_recording_holds_what_the_scene_says(recording):
    rec = recording
    scene = make_scene("jumpingjack", "small")
    assert (rec.width, rec.height) == (173, 130)
    assert list(rec.anchors.t_us) == [0, 100_000, 200_000, 300_000]
    assert len(rec.held_out) == 6 and rec.held_out.t_us[0] == 33_333
    assert rec.anchors.images.dtype == np.uint8 and rec.anchors.images.shape == (4, 130, 173, 3)
    # frames and poses are the scene's at those instants
    expected = np.round(render(scene, 0.1) * 255).astype(np.uint8)
    np.testing.assert_array_equal(rec.anchors.images[1], expected)
    np.testing.assert_allclose(rec.held_out.poses[2], scene.camera_at(rec.held_out.t_us[2] * 1e-6))
    k = scene.intrinsics
    np.testing.assert_allclose(rec.intrinsics, [k.fx, k.fy, k.cx, k.cy])
    # the dense trajectory agrees with the frame poses
    traj = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w)
    np.testing.assert_allclose(traj.at(rec.held_out.t_us[3]), rec.held_out.poses[3], atol=1e-6)
    assert rec.contrast_threshold == 0.2 and rec.sensor == "simulated"
    ev = rec.events
    assert len(ev) > 1000 and np.all(np.diff(ev.t) >= 0) and ev.t[0] > 0 and ev.t[-1] <= 300_000
    meta = rec.metadata
    assert meta["scene"] == "jumpingjack" and meta["fps"] == 10.0 and meta["seed"] == 0
    assert meta["simulator"]["contrast_threshold"] == 0.2 and meta["simulator"]["eps"] == 1e-3
    assert meta["sampling"]["samples"] == 31 and meta["gaussians"] == len(scene.gaussians_at(0.0))
    # the IMU on the camera: 1 kHz over the span, gravity (1 g) and the camera's turning, in dv's units
    imu = rec.imu
    assert len(imu) == 301 and np.all(np.diff(imu["t"]) == 1000)
    assert 0.9 < np.median(np.linalg.norm(imu["accel"], axis=1)) < 1.1
    turned = np.radians(np.mean(imu["gyro"], axis=0)) * 0.3  # rad over the 0.3 s
    first, last = (scene.camera_at(t)[:3, :3] for t in (0.0, 0.3))
    assert np.linalg.norm(turned) == pytest.approx(np.arccos((np.trace(first.T @ last) - 1) / 2), abs=0.01)
    assert set(meta["imu"]["biases"]) == {"gyro_dps", "accel_g"}


def test_events_match_the_anchor_frames_by_the_event_generation_model(recording):
    """C * sum(p) between two anchors ~ the change of their log luminance (within 2C, uint8 aside)."""
    rec = recording
    eps, c = rec.metadata["simulator"]["eps"], rec.contrast_threshold
    weights = np.asarray(rec.metadata["simulator"]["luma_weights"])
    log_l = np.log(rec.anchors.images.astype(np.float64) / 255 @ weights + eps)
    t0, t1 = rec.anchors.t_us[0], rec.anchors.t_us[2]
    sel = (rec.events.t > t0) & (rec.events.t <= t1)
    acc = np.zeros((rec.height, rec.width))
    np.add.at(acc, (rec.events.y[sel], rec.events.x[sel]), rec.events.p[sel])
    err = np.abs(c * acc - (log_l[2] - log_l[0]))
    # uint8 rounding of the anchors moves L by at most log((v + 0.5/255 + eps)/(v + eps)) per frame
    assert np.mean(err < 2 * c + 0.02) > 0.999 and np.abs(acc).max() >= 3


def test_round_trip_through_the_file(recording, tmp_path):
    from edmcgs.sensor.files.recording import write_recording

    path = write_recording(tmp_path / "rec.h5", recording)
    back = read_recording(path)
    assert back.events == recording.events
    np.testing.assert_array_equal(back.anchors.images, recording.anchors.images)
    np.testing.assert_array_equal(back.held_out.t_us, recording.held_out.t_us)
    np.testing.assert_array_equal(back.trajectory_c2w, recording.trajectory_c2w)
    np.testing.assert_array_equal(back.imu, recording.imu)
    assert back.metadata == recording.metadata and back.contrast_threshold == 0.2
    Intrinsics(*back.intrinsics, back.width, back.height)  # usable as the model's camera


def test_a_seed_makes_it_deterministic():
    sim = SimulatorConfig(threshold_sigma=0.03, noise_rate_hz=0.5)
    a = build_recording(_config(duration_s=0.1, simulator=sim, seed=3), progress=False)
    b = build_recording(_config(duration_s=0.1, simulator=sim, seed=3), progress=False)
    c = build_recording(_config(duration_s=0.1, simulator=sim, seed=4), progress=False)
    assert a.events == b.events and a.events != c.events
    np.testing.assert_array_equal(a.anchors.images, c.anchors.images)  # the scene itself has no seed
    assert a.metadata["simulator"]["seed"] == 3


def test_blur_averages_the_anchor_over_its_exposure():
    sharp = build_recording(_config(duration_s=0.1, held_out_per_interval=4), progress=False)
    blurred = build_recording(_config(duration_s=0.1, held_out_per_interval=4, blur=True), progress=False)
    exposure = blurred.metadata["blur"]["exposure_us"]
    assert exposure == 10_000  # 0.5 / (10 fps * 5 frames per interval)
    diff = np.abs(sharp.anchors.images.astype(int) - blurred.anchors.images.astype(int))
    assert diff.max() > 20  # moving limbs smear
    np.testing.assert_array_equal(sharp.held_out.images, blurred.held_out.images)
    assert blurred.events == sharp.events  # the event camera does not integrate


def test_bad_configs_name_the_parameter():
    with pytest.raises(InvalidInputError, match="scene"):
        BuildConfig(scene="teapot")
    with pytest.raises(InvalidInputError, match="fps"):
        BuildConfig(scene="kick", fps=0)
    with pytest.raises(InvalidInputError, match="size"):
        BuildConfig(scene="kick", size="medium")


@pytest.mark.slow
def test_the_command_writes_a_readable_file(tmp_path, capsys):
    out = tmp_path / "kick.h5"
    argv = ["kick", "--fps", "10", "--duration", "0.2", "-o", str(out), "--seed", "2", "-q",
            "--dt-min-us", "10000", "--dt-max-us", "10000"]
    assert main(argv) == 0
    rec = read_recording(out)
    assert rec.metadata["scene"] == "kick" and len(rec.anchors) == 3 and len(rec.held_out) == 8
    assert "kick.h5: kick 173x130" in capsys.readouterr().out
    assert main(["kick", "--fps", "-1", "-o", str(out), "-q"]) == 2
