"""The 3D street (``synth.street3d``) and its handheld DAVIS346 recording (``street3d_build``)."""

import math

import numpy as np
import pytest
from PIL import Image

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import validate_pose
from edmcgs.sensor.files.recording import read_recording, write_recording
from edmcgs.synth import street3d_textures as tx
from edmcgs.synth.cli import main as synth_main
from edmcgs.synth.davis import STANDARD_GRAVITY, ImuConfig, imu_samples, imu_truth
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig, simulate_render
from edmcgs.synth.procedural import value_noise
from edmcgs.synth.street3d import RIG, EventRender, HandheldPath, StreetScene
from edmcgs.synth.street3d_build import Street3dConfig, build_street3d

SMALL = dict(width=173, height=130)
TINY = SMALL | dict(duration_s=0.2, sampling=AdaptiveSampling(dt_max_us=4000, dt_min_us=2000, max_delta=2.0))
QUIET = ImuConfig(gyro_noise_dps=0.0, accel_noise_g=0.0, gyro_bias_dps=0.0, accel_bias_g=0.0)


@pytest.fixture(scope="module")
def recording():
    return build_street3d(Street3dConfig(**TINY), progress=False)


@pytest.fixture(scope="module")
def scene():
    return StreetScene(**SMALL, seed=0)


def _rotvec(r: np.ndarray) -> np.ndarray:
    angle = math.acos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return w / (2 * math.sin(angle)) * angle if angle > 1e-12 else 0.5 * w


def test_the_hand_walks_along_the_street_looking_around_with_a_shake():
    t = np.arange(0.0, 4.0, 0.001)
    c2w = HandheldPath(0).c2w(t)
    for pose in c2w[::500]:
        validate_pose(pose)
    p = c2w[:, :3, 3]
    assert 3.2 < p[-1, 0] - p[0, 0] < 4.0  # walking east at 0.9 m/s
    assert -6.5 < p[:, 1].min() and p[:, 1].max() < -5.5 and abs(np.ptp(p[:, 1])) > 0.1  # on the pavement
    assert np.all(np.abs(p[:, 2] - 1.5) < 0.03)
    view = c2w[:, :3, 2]  # the optical axis: along the street, towards its north side
    yaw = np.degrees(np.arctan2(view[:, 1], view[:, 0]))
    assert 0 < yaw.min() and yaw.max() < 40 and np.ptp(yaw) > 8
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert step.max() < 1.5e-3  # continuous: under 1.5 m/s
    turn = [np.linalg.norm(_rotvec(a[:3, :3].T @ b[:3, :3]))
            for a, b in zip(c2w[:-1:7], c2w[1::7], strict=True)]
    assert max(turn) < math.radians(0.1)  # under 100 degrees per second
    # the shake: what a 0.25 s moving average leaves of the position is a few millimetres
    kernel = np.ones(250) / 250
    residual = p[125:-125] - np.stack([np.convolve(p[:, i], kernel, "valid")[:-1] for i in range(3)], 1)
    rms = np.sqrt((residual ** 2).mean(axis=0))
    assert np.all((rms > 3e-4) & (rms < 5e-3)), rms
    still = HandheldPath(0, moving=False).c2w(t[::400])
    np.testing.assert_array_equal(still, np.repeat(still[:1], len(still), axis=0))


def test_the_imu_reads_the_motion_of_the_poses():
    path = HandheldPath(3)
    t_us = np.arange(500_000, 1_500_001, 1000, dtype=np.int64)
    gyro, force = imu_truth(path.c2w, t_us * 1e-6)
    imu, biases = imu_samples(t_us, gyro, force, QUIET, np.random.default_rng(0))
    assert biases == {"gyro_dps": [0.0, 0.0, 0.0], "accel_g": [0.0, 0.0, 0.0]}
    w = np.radians(imu["gyro"].astype(np.float64))  # dv's units back to SI
    f = imu["accel"].astype(np.float64) * STANDARD_GRAVITY
    c2w = path.c2w(t_us * 1e-6)
    # integrating the gyro gives the rotation between the poses (body rates, midpoint rule)
    r = c2w[0, :3, :3].copy()
    for k in range(len(t_us) - 1):
        v = 0.5 * (w[k] + w[k + 1]) * 1e-3
        a = np.linalg.norm(v)
        kx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        r = r @ (np.eye(3) + math.sin(a) / a * kx + (1 - math.cos(a)) / a ** 2 * kx @ kx)
    assert np.linalg.norm(_rotvec(r.T @ c2w[-1, :3, :3])) < 2e-4  # rad, after 1 s
    # the accelerometer minus gravity, turned to the world and integrated twice, gives the path
    acc = np.einsum("kij,kj->ki", c2w[:, :3, :3], f) + np.array([0.0, 0.0, -STANDARD_GRAVITY])
    v0 = (path.c2w([0.5 + 1e-4])[0, :3, 3] - path.c2w([0.5 - 1e-4])[0, :3, 3]) / 2e-4
    vel = v0 + np.concatenate([[[0.0] * 3], np.cumsum(0.5 * (acc[1:] + acc[:-1]) * 1e-3, axis=0)])
    pos = c2w[0, :3, 3] + np.concatenate([[[0.0] * 3], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * 1e-3, axis=0)])
    assert np.abs(pos - c2w[:, :3, 3]).max() < 2e-3  # metres, after 1 s
    # a camera held still reads gravity only: 1 g, "up" in its own axes
    still = HandheldPath(3, moving=False)
    gyro, force = imu_truth(still.c2w, np.array([0.2, 0.7]))
    np.testing.assert_allclose(gyro, 0.0, atol=1e-9)
    up = still.c2w([0.0])[0, :3, :3].T @ [0, 0, STANDARD_GRAVITY]
    np.testing.assert_allclose(force, np.tile(up, (2, 1)), atol=1e-6)
    # noise and bias as configured
    t_us = np.arange(0, 2_000_001, 1000, dtype=np.int64)
    gyro, force = imu_truth(path.c2w, t_us * 1e-6)
    noisy, biases = imu_samples(t_us, gyro, force, ImuConfig(), np.random.default_rng(1))
    err = noisy["gyro"] - np.degrees(gyro)
    np.testing.assert_allclose(err.mean(axis=0), biases["gyro_dps"], atol=0.02)
    np.testing.assert_allclose(err.std(axis=0), 0.1, rtol=0.1)


def test_cars_drive_through_the_view(scene):
    seen = {}
    for t in np.arange(0.0, 4.0, 0.25):
        cars = scene.cars_at(t)
        windows = scene.car_windows(t, scene.camera_at(t))
        assert cars and windows
        for car in cars:
            seen[(car.lane, car.slot)] = car
    assert {car.direction for car in seen.values()} == {-1, 1} and len(seen) >= 6
    assert all(6.9 < car.speed < 10.1 for car in seen.values())
    car = next(c for c in scene.cars_at(1.0) if c.direction < 0 and 10 < c.x_at(1.0) < 60)
    assert car.x_at(1.5) == pytest.approx(car.x_at(1.0) - 0.5 * car.speed)
    assert scene.cars_at(1.0) == scene.cars_at(1.0)  # a function of time: traffic is deterministic


def test_the_car_pixels_are_where_the_frame_differs_from_the_street_without_cars(scene):
    t = 1.0
    c2w = scene.camera_at(t)
    cars = scene.car_pixels(t, c2w)
    differs = scene.frame(t, c2w).quad != scene.static_frame(c2w).quad
    assert cars.shape == (scene.height, scene.width) and cars.any()
    assert np.array_equal(cars, differs)  # a car's quad covers the street behind it, nothing else does
    inside = np.zeros_like(cars)
    for x0, y0, x1, y1 in scene.car_windows(t, c2w):
        inside[y0:y1, x0:x1] = True
    assert not (cars & ~inside).any()


def _events(scene, t0_us, t1_us):
    sampling = AdaptiveSampling(dt_max_us=4000, dt_min_us=1000, max_delta=2.0)
    return simulate_render(EventRender(scene), t0_us, t1_us, SimulatorConfig(), sampling)[0]


def test_events_fire_where_cars_move_and_where_the_camera_moves():
    t0, t1 = 1_000_000, 1_150_000
    empty = StreetScene(**SMALL, seed=0, occupancy=0.0, moving_camera=False)
    assert len(_events(empty, t0, t1)) == 0  # a still camera on an empty street: nothing (no noise here)
    traffic = StreetScene(**SMALL, seed=0, moving_camera=False)
    ev = _events(traffic, t0, t1)
    near_cars = np.zeros((traffic.height, traffic.width), bool)
    for t in range(t0, t1 + 1, 5000):
        for x0, y0, x1, y1 in traffic.car_windows(t * 1e-6, traffic.camera_at(t * 1e-6)):
            near_cars[y0:y1, x0:x1] = True
    assert len(ev) > 1000
    assert near_cars[ev.y, ev.x].mean() > 0.99  # the street is still: events come from the cars
    by_cars = _fired(ev, traffic)
    walking = StreetScene(**SMALL, seed=0, occupancy=0.0)
    by_walking = _fired(_events(walking, t0, t1), walking)
    assert by_walking.mean() > 0.2 and by_walking.mean() > 3 * by_cars.mean()  # the whole street moves


def _fired(ev, scene) -> np.ndarray:
    fired = np.zeros((scene.height, scene.width), bool)
    fired[ev.y, ev.x] = True
    return fired


def test_the_event_render_is_the_frame_up_to_its_interpolation(scene):
    render = EventRender(scene)
    for t_us in (1_000_000, 1_001_000, 2_343_500):
        approx, exact = render(t_us), scene.render(t_us * 1e-6)
        err = np.abs(np.log(approx + 1e-3) - np.log(exact + 1e-3))
        assert np.quantile(err, 0.999) < 0.05 and err.max() < 0.5
    np.testing.assert_allclose(render(2_000_000), scene.render(2.0), atol=1e-12)  # on a keyframe: exact
    assert render.renders <= 6


def test_the_novel_camera_sees_the_street_from_the_rig(scene):
    t = 1.3
    c2w, novel = scene.camera_at(t), scene.novel_camera_at(t)
    np.testing.assert_allclose(novel, c2w @ RIG)
    assert np.linalg.norm(novel[:3, 3] - c2w[:3, 3]) == pytest.approx(0.3)
    a, b = scene.frame(t), scene.frame(t, novel)
    assert np.abs(a.luminance - b.luminance).mean() > 0.02  # another view
    # every pixel of the event camera, moved to the world by its depth and into the novel camera,
    # lands on the same quad there (but where an edge or an occlusion is near)
    k = scene.intrinsics
    ys, xs = np.nonzero(np.isfinite(a.depth))
    cam = np.stack([(xs - k.cx) / k.fx, (ys - k.cy) / k.fy, np.ones(len(xs))], 1) * a.depth[ys, xs, None]
    world = cam @ c2w[:3, :3].T + c2w[:3, 3]
    other = (world - novel[:3, 3]) @ novel[:3, :3]
    u = np.round(k.fx * other[:, 0] / other[:, 2] + k.cx).astype(int)
    v = np.round(k.fy * other[:, 1] / other[:, 2] + k.cy).astype(int)
    inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    assert inside.mean() > 0.8
    assert np.mean(b.quad[v[inside], u[inside]] == a.quad[ys[inside], xs[inside]]) > 0.9


def test_a_recording_is_deterministic_and_round_trips(recording, tmp_path):
    rec = recording
    again = build_street3d(Street3dConfig(**TINY), progress=False)
    assert again.events == rec.events and again.anchors == rec.anchors and again.held_out == rec.held_out
    assert again.novel_views == rec.novel_views and np.array_equal(again.imu, rec.imu)
    other = build_street3d(Street3dConfig(**TINY | {"seed": 1}), progress=False)
    assert other.events != rec.events and not np.array_equal(other.imu["gyro"], rec.imu["gyro"])
    assert not np.array_equal(other.anchors.images, rec.anchors.images)
    back = read_recording(write_recording(tmp_path / "s.h5", rec))
    assert back.events == rec.events and back.anchors == rec.anchors and back.held_out == rec.held_out
    assert back.novel_views == rec.novel_views and np.array_equal(back.imu, rec.imu)
    assert back.metadata == rec.metadata and back.metadata["scene"] == "street3d"


def test_a_recording_holds_the_sensor_the_trajectory_and_the_novel_views(recording):
    rec = recording
    assert (rec.width, rec.height) == (173, 130) and len(rec.anchors) == 2 and len(rec.held_out) == 4
    assert rec.anchors.channels == 1 and rec.contrast_threshold == pytest.approx(0.2)
    assert len(rec.events) > 10_000 and rec.events.t_end <= 200_000
    # poses: each frame's is the trajectory's at its time; the novel views' are those times the rig
    traj = dict(zip(rec.trajectory_t_us.tolist(), rec.trajectory_c2w, strict=True))
    for frames in (rec.anchors, rec.held_out):
        for t, pose in zip(frames.t_us, frames.poses, strict=True):
            np.testing.assert_allclose(pose, traj[int(t)], atol=1e-12)
    np.testing.assert_array_equal(rec.novel_views.t_us, rec.held_out.t_us)
    np.testing.assert_allclose(rec.novel_views.poses, rec.held_out.poses @ RIG, atol=1e-12)
    assert np.abs(rec.novel_views.images.astype(int) - rec.held_out.images).mean() > 3
    # the IMU at 1 kHz over the span, in g and degrees per second
    assert len(rec.imu) == 201 and np.all(np.diff(rec.imu["t"]) == 1000)
    assert 0.8 < np.median(np.linalg.norm(rec.imu["accel"], axis=1)) < 1.4  # gravity, and the hand
    assert rec.metadata["imu"]["units"] == "accel g, gyro degrees per second"
    assert rec.metadata["novel_views"]["rig"] == RIG.tolist()


def test_the_command_writes_the_recording_and_its_contact_sheet(tmp_path):
    out, sheet = tmp_path / "street.h5", tmp_path / "street.png"
    assert synth_main(["street3d", "-o", str(out), "--size", "small", "--seconds", "0.2", "--seed", "2",
                       "--dt-min-us", "2000", "--sheet", str(sheet), "-q"]) == 0
    rec = read_recording(out)
    assert rec.metadata["scene"] == "street3d" and rec.metadata["seed"] == 2 and rec.width == 173
    assert rec.metadata["sampling"]["dt_min_us"] == 2000 and rec.novel_views is not None
    with Image.open(sheet) as img:
        assert img.size == (4 * 346, 2 * (260 + 14))
    assert synth_main(["street3d", "-o", str(tmp_path / "x.h5"), "--fps", "7", "-q"]) == 2


def test_bad_settings_are_refused():
    with pytest.raises(InvalidInputError, match="fps"):
        Street3dConfig(fps=7.0)
    with pytest.raises(InvalidInputError, match="width"):
        Street3dConfig(width=4)
    with pytest.raises(InvalidInputError, match="occupancy"):
        StreetScene(**SMALL, occupancy=1.5)
    with pytest.raises(InvalidInputError, match="keyframe"):
        Street3dConfig(keyframe_us=0)
    with pytest.raises(InvalidInputError, match="finite"):
        StreetScene(**SMALL).camera_at(float("nan"))


def test_tiling_textures_repeat_without_seams():
    # across the wrap, a texture differs from itself no more than between two neighbouring texels (the
    # road along the street, where it repeats; plaster and soil both ways)
    for img, both in ((tx.road(7, 2)[0], False), (tx.wall(7, 2)[0], True), (tx.soil(7, 2)[0], True)):
        assert np.abs(img[:, 0] - img[:, -1]).mean() < 2 * np.abs(np.diff(img, axis=1)).mean()
        if both:
            assert np.abs(img[0] - img[-1]).mean() < 2 * np.abs(np.diff(img, axis=0)).mean()
        assert 0.0 < img.min() and img.max() < 0.95
    u = np.linspace(-3.0, 3.0, 301)
    for spacing in (0.32, 0.04):
        a = value_noise(u, 2 * u, spacing, 5, period=5.12)
        b = value_noise(u + 5.12, 2 * u - 10.24, spacing, 5, period=5.12)
        np.testing.assert_allclose(a, b, atol=1e-12)
    with pytest.raises(InvalidInputError, match="power of two"):
        value_noise(u, u, 0.3, 5, period=5.12)
