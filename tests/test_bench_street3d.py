"""bench.street3d's scoring: a novel view from the held-out camera is the held-out render, the cars'
mask is their pixels widened within the frame, and the moving-pixel PSNR counts those pixels alone."""

import numpy as np
import pytest

from bench import street3d
from edmcgs.model.eval.evaluation import render_held_out
from edmcgs.model.eval.metrics import psnr
from edmcgs.synth.street3d import StreetScene
from tests.support.models import build, one_torch_thread  # noqa: F401


def test_a_view_from_the_held_out_camera_is_the_held_out_render():
    model, data = build()
    for i in data.evaluable().tolist():
        t = int(data.held_out_t_us[i])
        expected = render_held_out(model, data, i)[0]
        assert expected.max() > 0.1  # the square is in view
        assert np.array_equal(street3d.render_view(model, data, t, data.held_out_pose(i)), expected)
        shifted = data.held_out_pose(i).copy()
        shifted[0, 3] += 0.3
        assert not np.array_equal(street3d.render_view(model, data, t, shifted), expected)


def test_the_cars_mask_widens_their_pixels_and_stops_at_the_frame():
    scene = StreetScene(173, 130, seed=0)
    m = street3d.CAR_MARGIN
    for t_s in (0.5, 1.0, 2.0):
        c2w = scene.camera_at(t_s)
        cars = scene.car_pixels(t_s, c2w)
        mask = street3d.car_mask(scene, int(t_s * 1e6), c2w)
        ys, xs = np.nonzero(cars)
        assert cars.any() and (mask & cars).sum() == cars.sum()
        # every masked pixel lies within the margin of a car pixel (no wrap-around to the far edge)
        for y, x in zip(*np.nonzero(mask), strict=True):
            assert (np.maximum(abs(ys - y), abs(xs - x)) <= m).any()
        # and every pixel within the margin of one is masked
        for y, x in ((ys[0] - m, xs[0]), (ys[-1] + m, xs[-1]), (ys[0], xs[0] - m)):
            if 0 <= y < scene.height and 0 <= x < scene.width:
                assert mask[y, x]


def test_the_moving_psnr_counts_the_masked_pixels_alone():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.2, 0.8, (20, 30, 1)).astype(np.float32)
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:10, 5:15] = True
    image = truth.copy()
    image[mask] += 0.1  # 20 dB on the masked pixels
    image[~mask] += 0.01  # 40 dB elsewhere
    scores = street3d.Scores()
    scores.add("a", image, truth, mask)
    scores.add("a", truth + 0.01, truth, mask)  # 40 dB everywhere
    s = scores.summary()["a"]
    assert s["frames"] == 2
    assert s["psnr"] == pytest.approx((psnr(image, truth) + psnr(truth + 0.01, truth)) / 2)
    # the squared errors of both frames' masked pixels pooled: (0.1^2 + 0.01^2) / 2
    assert s["moving_psnr"] == pytest.approx(-10 * np.log10((0.1 ** 2 + 0.01 ** 2) / 2), abs=1e-3)


def test_a_model_with_its_own_poses_renders_held_out_frames_from_them():
    """A model whose poses were estimated (its own world frame) is scored from its own trajectory, as
    bench.cold_start scores a learnt model on a recording without poses."""
    from dataclasses import replace

    from edmcgs.geometry import Trajectory

    model, data = build()
    i = int(data.evaluable()[0])
    own = render_held_out(model, data, i, own_poses=True)[0]
    assert np.array_equal(own, render_held_out(model, data, i)[0])  # the same poses: the same render
    traj = model.meta.trajectory
    moved = traj.c2w.copy()
    moved[:, 0, 3] += 0.3
    model.meta = replace(model.meta, trajectory=Trajectory(traj.t_us, moved))
    assert not np.array_equal(render_held_out(model, data, i, own_poses=True)[0], own)


def test_the_offline_run_of_a_recording_without_poses_gets_what_the_service_was_sent(tmp_path):
    """bench.cold_start trains its offline comparison on the frames the replay sends (the anchors): its
    structure from motion sees no held-out frame, as the learner's does not."""
    from bench.cold_start import sent
    from edmcgs.sensor.files.recording import read_recording
    from tests.support.recordings import write_tiny_h5

    rec_path = write_tiny_h5(tmp_path / "tiny.h5")
    full = read_recording(rec_path)
    copy = read_recording(sent(rec_path, tmp_path / "cache"))
    assert full.held_out is not None and copy.held_out is None
    assert np.array_equal(copy.anchors.t_us, full.anchors.t_us)
    assert np.array_equal(copy.anchors.images, full.anchors.images)
    assert len(copy.events) == len(full.events) and np.array_equal(copy.events.t, full.events.t)
    assert np.array_equal(copy.intrinsics, full.intrinsics)
    assert copy.contrast_threshold == full.contrast_threshold
