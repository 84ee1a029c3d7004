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
    t = int(data.held_out_t_us[i])
    own = render_held_out(model, data, i, camera=model.meta.trajectory.at(t))[0]
    assert np.array_equal(own, render_held_out(model, data, i)[0])  # the same poses: the same render
    traj = model.meta.trajectory
    moved = traj.c2w.copy()
    moved[:, 0, 3] += 0.3
    model.meta = replace(model.meta, trajectory=Trajectory(traj.t_us, moved))
    assert not np.array_equal(render_held_out(model, data, i, camera=model.meta.trajectory.at(t))[0], own)


def test_registered_cameras_carry_the_reference_poses_into_each_models_frame():
    """bench.cold_start scores each model from the same registered poses: the reference's pose at a held-out
    time, moved by the similarity that aligns the anchors, not the model's interpolation between them."""
    from types import SimpleNamespace

    from bench.cold_start import registered_cameras
    from edmcgs.geometry import Similarity, Trajectory

    t = np.arange(0, 2_000_001, 40_000, dtype=np.int64)
    angle = 0.8 * t / 2e6
    c2w = np.tile(np.eye(4), (len(t), 1, 1))
    c2w[:, 0, 0], c2w[:, 0, 2], c2w[:, 2, 0], c2w[:, 2, 2] = np.cos(angle), np.sin(angle), -np.sin(angle), \
        np.cos(angle)
    c2w[:, :3, 3] = np.stack([np.sin(3 * angle), 0.1 * angle**2, angle], axis=1)
    reference = Trajectory(t, c2w)
    anchors = t[::5]
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    to_model = Similarity(2.5, rot, np.array([1.0, -2.0, 0.5]))

    def model(traj):
        return SimpleNamespace(meta=SimpleNamespace(trajectory=traj))

    learnt = Trajectory(anchors, to_model.poses(reference.at(anchors)))
    still = Trajectory(anchors[:1], c2w[:1])
    models = {"offline": model(reference), "learnt": model(learnt), "still": model(still)}
    cameras = registered_cameras(reference, models, anchors)
    held = int(t[7])  # between two anchors
    assert np.allclose(cameras["offline"](held), reference.at(held), atol=1e-9)
    expected = to_model.poses(reference.at(held))[0]
    assert np.allclose(cameras["learnt"](held), expected, atol=1e-9)
    assert not np.allclose(models["learnt"].meta.trajectory.at(held), expected, atol=1e-3)  # interpolated
    assert np.allclose(cameras["still"](held), c2w[0])  # no similarity from a camera that did not move
