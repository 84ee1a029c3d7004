"""Camera model: intrinsics, rotations, pose validation and wire parsing, projection, trajectories,
similarities between world frames."""

import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError, PoseError
from edmcgs.geometry import (
    Intrinsics,
    Similarity,
    Trajectory,
    parse_pose,
    pose_from_quat,
    project,
    quat_multiply,
    quat_to_rotmat,
    rotmat_to_quat,
    validate_pose,
    world_to_camera,
)

RNG = np.random.default_rng(0)


def random_quats(n):
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_pose():
    return pose_from_quat(RNG.normal(size=3), random_quats(1)[0])


# ------------------------------------------------------------------------------------ intrinsics

def test_intrinsics_matrix_and_scaling_keep_pixel_edges():
    k = Intrinsics(200.0, 210.0, 172.5, 129.5, 346, 260)
    assert np.array_equal(k.matrix(), [[200, 0, 172.5], [0, 210, 129.5], [0, 0, 1]])
    half = k.scaled(173, 130)
    assert (half.width, half.height) == (173, 130)
    assert half.fx == pytest.approx(100.0) and half.fy == pytest.approx(105.0)
    # a centred principal point stays centred: (W - 1) / 2
    assert half.cx == pytest.approx(86.0) and half.cy == pytest.approx(64.5)
    # the same ray lands on the same place in the image, measured in pixel edges
    uv, _ = project(np.array([[0.3, -0.2, 2.0]]), np.eye(4), k)
    uv2, _ = project(np.array([[0.3, -0.2, 2.0]]), np.eye(4), half)
    np.testing.assert_allclose((uv2 + 0.5) * 2, uv + 0.5)


@pytest.mark.parametrize("kwargs, field", [
    (dict(fx=0.0), "fx"), (dict(fy=-1.0), "fy"), (dict(cx=float("nan")), "cx"), (dict(cy=float("inf")), "cy"),
    (dict(width=0), "width"), (dict(height=2.5), "height"), (dict(fx="200"), "fx"),
])
def test_intrinsics_reject_bad_fields_by_name(kwargs, field):
    base = dict(fx=200.0, fy=200.0, cx=10.0, cy=10.0, width=20, height=20)
    base.update(kwargs)
    with pytest.raises(InvalidInputError, match=field):
        Intrinsics(**base)


def test_intrinsics_are_frozen():
    k = Intrinsics(1.0, 1.0, 0.0, 0.0, 1, 1)
    with pytest.raises(AttributeError):
        k.fx = 2.0


# ------------------------------------------------------------------------------------- rotations

def test_quaternion_round_trip_all_branches():
    qs = np.concatenate([random_quats(500),
                         [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0]]])
    R = quat_to_rotmat(qs)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    back = rotmat_to_quat(R)
    assert (back[:, 0] >= 0).all()
    # q and -q are the same rotation
    sign = np.sign(np.sum(back * qs, axis=1))[:, None]
    np.testing.assert_allclose(back * sign, qs, atol=1e-10)


def test_quat_to_rotmat_matches_axis_angle():
    angle = 0.7
    R = quat_to_rotmat([np.cos(angle / 2), 0, 0, np.sin(angle / 2)])
    expect = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    np.testing.assert_allclose(R, expect, atol=1e-15)


def test_quat_multiply_composes_rotations_in_numpy_and_torch_alike():
    a, b = random_quats(50), random_quats(50)
    product = quat_multiply(a, b)
    assert product.dtype == np.float64
    np.testing.assert_allclose(quat_to_rotmat(product), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-12)
    np.testing.assert_allclose(quat_multiply(a[0].tolist(), b), quat_multiply(a[:1], b))  # lists broadcast
    torch_product = quat_multiply(torch.from_numpy(a), torch.from_numpy(b))
    assert isinstance(torch_product, torch.Tensor)
    np.testing.assert_allclose(torch_product.numpy(), product, atol=1e-15)


def test_quat_to_rotmat_normalises_and_rejects_zero_and_nan():
    np.testing.assert_allclose(quat_to_rotmat([2.0, 0, 0, 0]), np.eye(3))
    with pytest.raises(PoseError, match="zero"):
        quat_to_rotmat([0.0, 0, 0, 0])
    with pytest.raises(PoseError, match="non-finite"):
        quat_to_rotmat([np.nan, 0, 0, 1])


# ----------------------------------------------------------------------------------------- poses

def test_world_to_camera_inverts_c2w():
    poses = np.stack([random_pose() for _ in range(5)])
    w2c = world_to_camera(poses)
    np.testing.assert_allclose(w2c @ poses, np.broadcast_to(np.eye(4), poses.shape), atol=1e-12)
    np.testing.assert_allclose(world_to_camera(poses[0]), np.linalg.inv(poses[0]), atol=1e-12)


def test_validate_pose_reorthonormalises_small_rounding():
    pose = random_pose()
    rounded = np.round(pose, 4)
    out = validate_pose(rounded)
    R = out[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(out, pose, atol=1e-3)
    assert out.dtype == np.float64


@pytest.mark.parametrize("mutate, message", [
    (lambda m: m.__setitem__((0, 3), np.nan), "non-finite"),
    (lambda m: m.__setitem__((1, 1), np.inf), "non-finite"),
    (lambda m: m.__setitem__((0, 0), 1.1), "not orthonormal"),
    (lambda m: m.__setitem__(slice(0, 3), m[:3] * [[1], [1], [1]] * 2), "not orthonormal"),
    (lambda m: m.__setitem__((3, 0), 0.5), "bottom row"),
    (lambda m: m.__setitem__((3, 3), 2.0), "bottom row"),
    (lambda m: m.__setitem__((slice(None), 0), -m[:, 0]), "determinant -1"),
])
def test_validate_pose_names_the_problem(mutate, message):
    m = np.eye(4)
    m[:3, 3] = [1, 2, 3]
    mutate(m)
    with pytest.raises(PoseError, match=message):
        validate_pose(m, name="pose")


def test_validate_pose_rejects_wrong_shape_and_text():
    with pytest.raises(PoseError, match="4x4"):
        validate_pose(np.eye(3))
    with pytest.raises(PoseError, match="4x4"):
        validate_pose([["a"] * 4] * 4)


def test_parse_pose_sixteen_numbers_row_major():
    pose = random_pose()
    for value in (pose.reshape(-1).tolist(), pose, torch.tensor(pose),
                  ",".join(repr(float(x)) for x in pose.flat), " ".join(repr(float(x)) for x in pose.flat)):
        np.testing.assert_allclose(parse_pose(value), pose, atol=1e-12)


def test_parse_pose_seven_numbers_translation_then_wxyz():
    q = np.array([np.cos(0.35), 0.0, np.sin(0.35), 0.0])
    got = parse_pose(f"1, 2, 3, {q[0]}, {q[1]}, {q[2]}, {q[3]}")
    np.testing.assert_allclose(got[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(got[:3, :3], quat_to_rotmat(q), atol=1e-15)
    np.testing.assert_allclose(got[3], [0, 0, 0, 1])
    # a non-unit quaternion is the same rotation
    np.testing.assert_allclose(parse_pose([1, 2, 3, *(3 * q)]), got, atol=1e-12)


@pytest.mark.parametrize("value, message", [
    ("1,2,3", "16 numbers .* or 7"),
    ("1,2,3,a,5,6,7", "comma-separated"),
    ("", "got 0"),
    ([0, 0, 0, 0, 0, 0, 0], "zero"),
    ([0, 0, np.nan, 1, 0, 0, 0], "non-finite"),
    ("nan," + ",".join(["0"] * 15), "non-finite"),
    ([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 1, 2, 3, 1], "bottom row"),  # column-major sent by mistake,
])
def test_parse_pose_errors_name_the_problem(value, message):
    with pytest.raises(PoseError, match=message):
        parse_pose(value, name="pose")


# ------------------------------------------------------------------------------------ projection

def test_project_numpy_and_torch_agree_and_match_the_pinhole_formula():
    k = Intrinsics(100.0, 120.0, 50.0, 40.0, 101, 81)
    w2c = world_to_camera(random_pose())
    pts = RNG.normal(size=(50, 3)) * 3
    uv, z = project(pts, w2c, k)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(z, cam[:, 2])
    np.testing.assert_allclose(uv[:, 0], 100 * cam[:, 0] / cam[:, 2] + 50)
    np.testing.assert_allclose(uv[:, 1], 120 * cam[:, 1] / cam[:, 2] + 40)
    tp = torch.tensor(pts, requires_grad=True)
    uv_t, z_t = project(tp, torch.tensor(w2c), k)
    np.testing.assert_allclose(uv_t.detach().numpy(), uv)
    np.testing.assert_allclose(z_t.detach().numpy(), z)
    uv_t.sum().backward()
    assert torch.isfinite(tp.grad).all()


def test_project_optical_axis_and_points_on_the_camera_plane_stay_finite():
    k = Intrinsics(100.0, 100.0, 10.0, 20.0, 21, 41)
    uv, z = project(np.array([[0, 0, 5.0], [1, 1, 0.0], [0, 0, 0.0]]), np.eye(4), k)
    np.testing.assert_allclose(uv[0], [10, 20])
    assert np.isfinite(uv).all() and np.isfinite(z).all()
    uv_t, _ = project(torch.tensor([[1.0, 1.0, 0.0]]), np.eye(4), k)
    assert torch.isfinite(uv_t).all()
    assert uv_t.dtype == torch.float32


# ---------------------------------------------------------------------------------- trajectories

def test_trajectory_interpolates_slerp_and_linear_in_int64_microseconds():
    t0 = 1_700_000_000_000_000  # Unix-epoch µs: too big for float32
    angle = np.pi / 2
    q1 = [np.cos(angle / 2), 0, 0, np.sin(angle / 2)]
    traj = Trajectory(np.array([t0, t0 + 1_000_000], np.int64),
                      np.stack([pose_from_quat([0, 0, 0], [1, 0, 0, 0]), pose_from_quat([2, 4, 6], q1)]))
    mid = traj.at(t0 + 500_000)
    np.testing.assert_allclose(mid[:3, 3], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(mid[:3, :3], quat_to_rotmat([np.cos(angle / 4), 0, 0, np.sin(angle / 4)]),
                               atol=1e-12)
    # 1 µs resolution survives at Unix-epoch magnitudes
    one = traj.at(t0 + 1)
    np.testing.assert_allclose(one[:3, 3], np.array([2, 4, 6]) * 1e-6, atol=1e-15)
    # clamped to the span, exact at the samples
    np.testing.assert_allclose(traj.at(t0 - 10**9), traj.c2w[0])
    np.testing.assert_allclose(traj.at(t0 + 10**12), traj.c2w[1], atol=1e-15)
    batch = traj.at(np.array([t0, t0 + 500_000, t0 + 1_000_000]))
    assert batch.shape == (3, 4, 4)
    np.testing.assert_allclose(batch[1], mid)
    assert not traj.is_static
    assert traj.start_us == t0 and traj.end_us == t0 + 1_000_000 and len(traj) == 2


def test_trajectory_takes_the_short_arc_and_handles_identical_rotations():
    q = random_quats(1)[0]
    a = pose_from_quat([0, 0, 0], q)
    traj = Trajectory(np.array([0, 10]), np.stack([a, a]))
    np.testing.assert_allclose(traj.at(5), a, atol=1e-12)
    assert traj.is_static
    # a 350 degree turn is interpolated as -10 degrees
    b = pose_from_quat([0, 0, 0], [np.cos(np.radians(175)), 0, 0, np.sin(np.radians(175))])
    mid = Trajectory(np.array([0, 10]), np.stack([np.eye(4), b])).at(5)
    expect = pose_from_quat([0, 0, 0], [np.cos(np.radians(-2.5)), 0, 0, np.sin(np.radians(-2.5))])
    np.testing.assert_allclose(mid, expect, atol=1e-12)


def test_single_sample_trajectory_is_static():
    p = random_pose()
    traj = Trajectory(np.array([5]), p[None])
    assert traj.is_static
    np.testing.assert_allclose(traj.at(123), p, atol=1e-12)
    assert traj.at(np.array([1, 2])).shape == (2, 4, 4)


@pytest.mark.parametrize("t, poses, message", [
    (np.array([0.0, 1.0]), np.stack([np.eye(4)] * 2), "integer"),
    (np.array([0, 0]), np.stack([np.eye(4)] * 2), "strictly increasing"),
    (np.array([], np.int64), np.zeros((0, 4, 4)), "non-empty"),
    (np.array([0, 1]), np.stack([np.eye(4)] * 3), "match"),
])
def test_trajectory_rejects_bad_input(t, poses, message):
    with pytest.raises(InvalidInputError, match=message):
        Trajectory(t, poses)


def test_trajectory_names_the_bad_pose():
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(PoseError, match=r"c2w\[1\]"):
        Trajectory(np.array([0, 1]), np.stack([np.eye(4), bad]))
    with pytest.raises(InvalidInputError, match="integer"):
        Trajectory(np.array([0, 1]), np.stack([np.eye(4)] * 2)).at(0.5)


def test_a_similarity_is_recovered_and_maps_cameras_with_what_they_see():
    rot = quat_to_rotmat(random_quats(1))[0]
    truth = Similarity(2.5, rot, np.array([1.0, -2.0, 0.5]))
    path = np.cumsum(RNG.normal(size=(30, 3)) * 0.1, axis=0)
    fit = Similarity.fit(path, truth.points(path))
    assert fit.scale == pytest.approx(2.5, rel=1e-9)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-9)
    np.testing.assert_allclose(fit.inverse().points(truth.points(path)), path, atol=1e-9)
    # a camera and a point it sees, both mapped: the point projects to the same pixel
    intr = Intrinsics(100.0, 100.0, 50.0, 40.0, 101, 81)
    c2w = pose_from_quat([0.2, 0.1, -0.3], random_quats(1)[0])
    point = (c2w @ [0.3, -0.2, 4.0, 1.0])[:3]
    uv, z = project(point[None], world_to_camera(c2w), intr)
    uv2, z2 = project(fit.points(point[None]), world_to_camera(validate_pose(fit.poses(c2w)[0])), intr)
    np.testing.assert_allclose(uv2, uv, atol=1e-7)
    assert z2[0] == pytest.approx(2.5 * z[0])
    with pytest.raises(InvalidInputError, match="one place"):
        Similarity.fit(np.zeros((5, 3)), path[:5])
    with pytest.raises(InvalidInputError, match="N >= 3"):
        Similarity.fit(path[:2], path[:2])


def test_a_similarity_fit_is_evo_s_alignment():
    from harness.pose_scenes import trajectory_error

    t_us = np.arange(20, dtype=np.int64) * 40_000
    truth = np.tile(np.eye(4), (20, 1, 1))
    truth[:, :3, 3] = np.cumsum(RNG.normal(size=(20, 3)), axis=0)
    estimated = Similarity(0.3, quat_to_rotmat(random_quats(1))[0], np.array([0.5, 0.0, 2.0])).poses(truth)
    estimated[:, :3, 3] += RNG.normal(size=(20, 3)) * 0.01  # noise: the fit is a compromise
    fit = Similarity.fit(estimated[:, :3, 3], truth[:, :3, 3])
    rmse = float(np.sqrt(np.mean(np.sum((fit.points(estimated[:, :3, 3]) - truth[:, :3, 3]) ** 2, 1))))
    ate, _ = trajectory_error(t_us, estimated, truth)
    assert rmse == pytest.approx(ate, rel=1e-6)


def test_a_similarity_of_cameras_on_a_line_is_fixed_by_their_orientations():
    n = 12
    cams = np.tile(np.eye(4), (n, 1, 1))
    cams[:, :3, 3] = np.linspace(0, 1, n)[:, None] * [1.0, 0.0, 0.0]  # a straight walk
    cams[:, :3, :3] = quat_to_rotmat(np.c_[np.ones(n), np.zeros(n), 0.05 * np.sin(np.arange(n)), np.zeros(n)])
    truth = Similarity(0.7, quat_to_rotmat(random_quats(1))[0], np.array([2.0, 1.0, -1.0]))
    fit = Similarity.fit_poses(cams, truth.poses(cams))
    assert fit.scale == pytest.approx(0.7, rel=1e-9)
    np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-9)
    np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-9)
    with pytest.raises(InvalidInputError, match="do not move"):
        Similarity.fit_poses(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1)))
