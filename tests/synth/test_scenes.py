"""The procedural scenes: valid Gaussians at any t, continuous motion and camera, textured renders."""

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import project, validate_pose, world_to_camera
from edmcgs.synth.esim import SimulatorConfig, simulate_frames
from edmcgs.synth.orbit import DAVIS346, look_at
from edmcgs.synth.scene import SCENES, make_scene, render


@pytest.fixture(scope="module", params=SCENES)
def scene(request):
    return make_scene(request.param, "small")


def test_gaussians_are_valid_over_the_whole_span(scene):
    counts = set()
    for t in np.linspace(-0.1, scene.duration_s + 0.1, 23):
        g = scene.gaussians_at(t)
        counts.add(len(g))
        for a in (g.means, g.quats, g.scales, g.opacities, g.colors):
            assert a.dtype == np.float32 and np.isfinite(a).all()
        np.testing.assert_allclose(np.linalg.norm(g.quats, axis=1), 1.0, atol=1e-5)
        assert (g.scales > 0).all() and ((g.opacities > 0) & (g.opacities <= 1)).all()
        assert ((g.colors >= 0) & (g.colors <= 1)).all()
    assert len(counts) == 1 and 1000 < counts.pop() < 6000  # "a few thousand" at the small size


def test_motion_and_camera_are_continuous_in_time(scene):
    dt = 1e-4
    for t in (0.0, 0.37, 1.21, scene.duration_s - dt):
        a, b = scene.gaussians_at(t), scene.gaussians_at(t + dt)
        # nothing moves faster than 30 m/s, and orientations turn by less than 0.05 rad in 0.1 ms
        assert np.abs(b.means - a.means).max() < 30 * dt
        assert (np.abs(np.sum(a.quats * b.quats, axis=1)) > np.cos(0.025)).all()
        np.testing.assert_allclose(b.scales, a.scales, rtol=1e-2, atol=1e-6)
        c0, c1 = scene.camera_at(t), scene.camera_at(t + dt)
        validate_pose(c0, atol=1e-9)
        assert np.abs(c1 - c0).max() < 1e-3


def test_the_object_moves_and_stays_in_view(scene):
    g0, g1 = scene.gaussians_at(0.0), scene.gaussians_at(0.1)
    assert np.abs(g1.means - g0.means).max() > 0.05  # something moves by more than 5 cm in 0.1 s
    for t in np.linspace(0, scene.duration_s, 9):
        g = scene.gaussians_at(t)
        uv, depth = project(g.means.astype(np.float64), world_to_camera(scene.camera_at(t)), scene.intrinsics)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < scene.intrinsics.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < scene.intrinsics.height) & (depth > 0.5)
        assert inside.mean() > 0.9


def test_renders_are_finite_textured_and_fire_events_on_the_moving_object(scene):
    t = 0.1 if scene.name == "kick" else 0.37  # mid-kick, mid-swing
    frames = [render(scene, t + k * 5e-3) for k in range(3)]
    img = frames[0]
    assert img.shape == (scene.intrinsics.height, scene.intrinsics.width, 3) and img.dtype == np.float32
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
    background = np.all(np.abs(img - np.asarray(scene.background, np.float32)) < 1e-3, axis=2)
    assert 0.05 < 1 - background.mean() < 0.9  # the object covers a good part of the frame, not all
    object_px = img[~background]
    assert object_px.std(axis=0).max() > 0.15  # textured, not flat-shaded
    ev = simulate_frames(np.array([0, 5000, 10_000], np.int64), frames, SimulatorConfig())
    assert len(ev) > 100
    assert not background[ev.y, ev.x].all()


def test_jumpingjack_between_anchors_is_not_an_interpolation_of_them():
    scene = make_scene("jumpingjack", "small")
    for k in range(10):  # 5 fps anchors at k / 5 s
        a, b = scene.gaussians_at(k / 5), scene.gaussians_at((k + 1) / 5)
        mid = scene.gaussians_at((k + 0.5) / 5)
        off = np.linalg.norm(mid.means - 0.5 * (a.means + b.means), axis=1)
        assert off.max() > 0.25  # the hands are far from where a blend of the anchors puts them


def test_sizes_and_names():
    full = make_scene("kick", "full")
    small = make_scene("kick", "small")
    assert (full.intrinsics.width, full.intrinsics.height) == (346, 260) and full.intrinsics == DAVIS346
    assert (small.intrinsics.width, small.intrinsics.height) == (173, 130)
    assert len(full.gaussians_at(0.0)) > 2 * len(small.gaussians_at(0.0))
    with pytest.raises(InvalidInputError, match="unknown scene"):
        make_scene("teapot")
    with pytest.raises(InvalidInputError, match="unknown size"):
        make_scene("kick", "huge")
    with pytest.raises(InvalidInputError, match="finite"):
        small.gaussians_at(float("nan"))


def test_a_sweeping_camera_keeps_to_the_arc_of_the_scene_s_own_duration():
    orbit, sweep = make_scene("jumpingjack", "small"), make_scene("jumpingjack", "small", "sweep")
    d = orbit.duration_s
    for t in np.linspace(0.0, d, 7):  # within the scene's duration both are the same camera
        np.testing.assert_array_equal(sweep.camera_at(t), orbit.camera_at(t))
    for t in (0.3, 0.9 * d):  # then it comes back over the same arc: at d + x where it was at d - x
        np.testing.assert_allclose(sweep.camera_at(d + t), orbit.camera_at(d - t), atol=1e-12)
        np.testing.assert_allclose(sweep.camera_at(2 * d + t), orbit.camera_at(t), atol=1e-12)
    # the orbit circles on to views never seen within it
    assert np.linalg.norm(orbit.camera_at(4 * d)[:3, 3] - orbit.camera_at(0)[:3, 3]) > 1.0
    with pytest.raises(InvalidInputError, match="unknown camera"):
        make_scene("kick", "small", "dolly")


def test_look_at_is_opencv():
    c2w = look_at(eye=(0.0, -3.0, 1.0), target=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(c2w[:3, 2], [0, 1, 0], atol=1e-12)  # z forward, towards the target
    np.testing.assert_allclose(c2w[:3, 0], [1, 0, 0], atol=1e-12)  # x right
    np.testing.assert_allclose(c2w[:3, 1], [0, 0, -1], atol=1e-12)  # y down
    uv, depth = project(np.array([[0.0, 0.0, 2.0]]), world_to_camera(c2w), DAVIS346)
    assert depth[0] == pytest.approx(3.0) and uv[0, 1] < DAVIS346.cy  # above the target: up in the image
