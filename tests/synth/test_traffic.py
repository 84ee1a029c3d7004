"""The composited street scene (``synth.traffic``) and its DAVIS346-like recording (``traffic_build``)."""

import math

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.pipeline import training_data
from edmcgs.sensor.files.recording import read_recording, write_recording
from edmcgs.synth.cli import main as synth_main
from edmcgs.synth.davis import aps_frame, read_out
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig
from edmcgs.synth.traffic import TrafficScene
from edmcgs.synth.traffic_build import TrafficConfig, build_traffic

COARSE = AdaptiveSampling(dt_max_us=4000, dt_min_us=4000)  # uniform 4 ms steps: quick
TINY = dict(width=86, height=65, duration_s=0.4, sampling=COARSE, subframes=4)


@pytest.fixture(scope="module")
def recording():
    return build_traffic(TrafficConfig(**TINY), progress=False)


@pytest.fixture(scope="module")
def static_full():
    return TrafficScene(seed=0)


def test_a_seed_makes_scene_and_recording_deterministic(recording):
    again = build_traffic(TrafficConfig(**TINY), progress=False)
    other = build_traffic(TrafficConfig(**TINY | {"seed": 1}), progress=False)
    assert again.events == recording.events and again.anchors == recording.anchors
    assert again.held_out == recording.held_out
    assert other.events != recording.events
    assert not np.array_equal(other.anchors.images, recording.anchors.images)
    a, b = TrafficScene(64, 48, seed=5), TrafficScene(64, 48, seed=5)
    np.testing.assert_array_equal(a.render(0.37), b.render(0.37))
    assert not np.array_equal(a.render(0.37), TrafficScene(64, 48, seed=6).render(0.37))


def test_objects_are_small_fast_and_cross_the_frame(static_full):
    scene = static_full
    seen = {}
    for t in np.arange(0.0, 4.0, 0.05):
        for obj in scene.objects_at(t):
            seen[(obj.lane, obj.slot)] = obj
    assert len(seen) >= 15
    for obj in seen.values():
        assert 5.0 <= obj.length <= 20.0 and obj.width <= obj.length and obj.width >= 3.0
        assert 100.0 <= abs(obj.u_speed) <= 400.0
    assert {math.copysign(1, o.u_speed) for o in seen.values()} == {-1.0, 1.0}  # both directions
    counts = [len(scene.objects_at(t, margin_px=-30.0)) for t in np.arange(0.0, 4.0, 0.25)]
    assert 4 <= np.mean(counts) <= 14  # several in view at a time
    # every object enters and leaves: one in view at t is gone 3 s later
    first = {(o.lane, o.slot) for o in scene.objects_at(1.0)}
    assert first and not first & {(o.lane, o.slot) for o in scene.objects_at(4.0)}


def test_rendered_objects_have_their_size_and_speed(static_full):
    """Measured on the images: the coverage of one car, and its displacement over 10 ms."""
    scene = static_full
    t = 1.0
    objs = [o for o in scene.objects_at(t) if o.kind == "car" and 30 < o.u_at(t) < 316
            and 30 < o.u_at(t + 0.01) < 316]
    assert objs
    for obj in objs[:3]:
        _, cov0 = scene.render_with_coverage(t)
        _, cov1 = scene.render_with_coverage(t + 0.01)
        rows = slice(round(obj.v - 6), round(obj.v + 7))
        cols = slice(round(obj.u_at(t) - 20), round(obj.u_at(t) + 21))
        c0 = cov0[rows, cols]
        assert abs(c0.sum() - obj.length * obj.width) < 0.12 * obj.length * obj.width  # rounded corners
        extent = c0.max(axis=0).sum()
        assert abs(extent - obj.length) < 1.0
        lo, hi = sorted((obj.u_at(t), obj.u_at(t + 0.01)))
        near = slice(round(lo - 12), round(hi + 13))  # this car only (the next one is >= 60 px away)
        xs = np.arange(cov0.shape[1])[near]
        centre = [(c[rows, near].sum(axis=0) * xs).sum() / c[rows, near].sum() for c in (cov0, cov1)]
        assert abs((centre[1] - centre[0]) / 0.01 - obj.u_speed) < 10.0


def test_exposure_blur_smears_a_moving_car_along_its_motion(static_full):
    scene = static_full
    empty = TrafficScene(seed=0, occupancy=0.0)  # the same street without traffic
    t_us = 1_000_000
    obj = next(o for o in scene.objects_at(1.0) if o.kind == "car" and 40 < o.u_at(1.0) < 306)
    bg = empty.render(1.0)
    sharp = scene.render(1.0)
    blurred = aps_frame(scene.render, t_us, 10_000, 20)
    row = round(obj.v)

    def extent(img):
        return int((np.abs(img[row] - bg[row]) > 0.01).sum())

    smear = abs(obj.u_speed) * 0.01
    assert abs(extent(blurred) - extent(sharp) - smear) < 3.0
    # the blur is an average over the exposure: the static street is untouched
    far = np.ones_like(bg, bool)
    for o in scene.objects_at(1.0, margin_px=10.0):
        far[max(0, round(o.v) - 10):round(o.v) + 12] = False
    np.testing.assert_allclose(blurred[far], sharp[far], atol=1e-12)
    assert np.isfinite(blurred).all() and 0.0 < blurred.min() and blurred.max() < 0.9


def test_read_noise_has_its_standard_deviation_and_is_quantised():
    rng = np.random.default_rng(0)
    flat = np.full((200, 300), 0.5)
    out = read_out(flat, 2.0, rng)
    assert out.dtype == np.uint8
    dn = out.astype(float) - 127.5
    assert abs(dn.mean()) < 0.05
    assert abs(dn.std() - math.sqrt(4.0 + 1 / 12)) < 0.05  # Gaussian + rounding
    np.testing.assert_array_equal(read_out(flat, 0.0, rng), np.full((200, 300), 128, np.uint8))
    assert read_out(np.array([[1.2, -0.3]]), 2.0, rng).tolist() == [[255, 0]]


def test_the_pan_poses_match_the_pixel_shift():
    pan = TrafficScene(173, 130, pan_px_s=25.0, seed=2, occupancy=0.0)
    k = pan.intrinsics
    a = pan.render(0.0)
    for t in (0.4, 1.2):
        c2w = pan.camera_at(t)
        r = c2w[:3, :3]
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(r[1], [0, 1, 0], atol=1e-12)  # a rotation about y
        np.testing.assert_array_equal(c2w[:3, 3], 0.0)
        expected = k.fx * r[0, 2] / r[0, 0]  # fx tan(theta): the centre pixel's shift
        b = pan.render(t)
        ys, x0 = slice(55, 75), slice(70, 100)
        shifts = np.arange(0, 30)
        ssd = [np.sum((b[ys, x0.start - s:x0.stop - s] - a[ys, x0]) ** 2) for s in shifts]
        i = int(np.argmin(ssd))
        sub = 0.5 * (ssd[i - 1] - ssd[i + 1]) / (ssd[i - 1] - 2 * ssd[i] + ssd[i + 1])
        assert abs(shifts[i] + sub - expected) < 0.25
        assert abs(expected - k.fx * math.tan(25.0 * t / 300.0)) < 1e-9  # theta = 25 px/s * t / 300 px
    assert np.array_equal(TrafficScene(seed=2).camera_at(1.0), np.eye(4))  # the static camera


def test_the_recording_loads_and_holds_out_every_other_25hz_frame(recording, tmp_path):
    back = read_recording(write_recording(tmp_path / "traffic.h5", recording))
    assert (back.width, back.height) == (86, 65)
    assert list(back.anchors.t_us) == [0, 200_000, 400_000]
    assert list(back.held_out.t_us) == [40_000 * k for k in range(1, 10) if k % 5]
    assert back.anchors.images.shape == (3, 65, 86, 1) and back.held_out.images.shape == (8, 65, 86, 1)
    np.testing.assert_array_equal(back.held_out.poses, np.broadcast_to(np.eye(4), (8, 4, 4)))
    assert back.contrast_threshold == 0.2 and back.metadata == recording.metadata
    assert "background" not in back.metadata  # no constant background colour for the model to assume
    data = training_data(back)
    assert data.channels == 1
    np.testing.assert_array_equal(data.evaluable(), np.arange(8))  # eval scores every held-out frame
    ev = back.events
    assert len(ev) > 1000 and np.all(np.diff(ev.t) >= 0) and 0 < ev.t[0] and ev.t[-1] <= 400_000
    for frames in (back.anchors, back.held_out):
        assert 5 < frames.images.mean() < 120 and frames.images.max() < 250  # not saturated


def test_pan_recording_poses_and_nothing_non_finite(tmp_path):
    rec = build_traffic(TrafficConfig(**TINY | {"pan": True, "duration_s": 0.2}), progress=False)
    scene = TrafficScene(86, 65, pan_px_s=12.0, seed=0)
    for frames in (rec.anchors, rec.held_out):
        for t, pose in zip(frames.t_us, frames.poses, strict=True):
            np.testing.assert_allclose(pose, scene.camera_at(t * 1e-6))
    assert np.isfinite(rec.trajectory_c2w).all() and np.isfinite(rec.intrinsics).all()
    assert rec.metadata["scene"] == "traffic-pan" and rec.metadata["pan_px_s"] == 12.0
    for t in np.linspace(-1.0, 5.0, 7):
        img = scene.render(t)
        assert np.isfinite(img).all() and img.min() > 0 and img.max() < 0.9


def test_bad_arguments_name_the_parameter():
    for kw, name in ((dict(width=0), "width"), (dict(height=2.5), "height"), (dict(seed=-1), "seed"),
                     (dict(pan_px_s=math.nan), "pan_px_s"), (dict(occupancy=1.5), "occupancy")):
        with pytest.raises(InvalidInputError, match=name):
            TrafficScene(**kw)
    with pytest.raises(InvalidInputError, match="t_s"):
        TrafficScene(32, 24).render(math.inf)
    for kw, name in ((dict(fps=4.0), "divide"), (dict(fps=0.0), "fps"), (dict(duration_s=-1.0), "duration"),
                     (dict(exposure_us=40_000), "exposure_us"), (dict(read_noise_dn=-1.0), "read_noise"),
                     (dict(subframes=0), "subframes"), (dict(pan_px_s=0.0), "pan_px_s")):
        with pytest.raises(InvalidInputError, match=name):
            TrafficConfig(**kw)
    with pytest.raises(InvalidInputError, match="fewer than 2 anchors"):
        build_traffic(TrafficConfig(**TINY | {"duration_s": 0.1}), progress=False)
    with pytest.raises(InvalidInputError, match="hot_pixel_fraction"):
        SimulatorConfig(hot_pixel_fraction=1.5)


def test_the_command_writes_a_readable_file(tmp_path, capsys):
    out = tmp_path / "tp.h5"
    argv = ["traffic-pan", "--size", "small", "--seconds", "0.2", "-o", str(out), "-q",
            "--dt-min-us", "4000", "--dt-max-us", "4000", "--seed", "3"]
    assert synth_main(argv) == 0
    rec = read_recording(out)
    assert rec.metadata["scene"] == "traffic-pan" and (rec.width, rec.height) == (173, 130)
    assert len(rec.anchors) == 2 and len(rec.held_out) == 4 and rec.metadata["seed"] == 3
    assert "tp.h5: traffic-pan 173x130" in capsys.readouterr().out
    assert synth_main(["traffic", "--fps", "4", "-o", str(out), "-q"]) == 2
    assert "must divide" in capsys.readouterr().err
