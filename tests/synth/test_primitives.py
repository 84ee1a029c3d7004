"""Surface Gaussians: on their shape, facing out along its normal, about one per spacing squared."""

import numpy as np

from edmcgs.geometry import quat_multiply, quat_to_rotmat
from edmcgs.synth.cloud import Cloud, axis_angle_quat, pose_parts, rotation
from edmcgs.synth.primitives import (
    NORMAL_SIGMA,
    TANGENT_SIGMA,
    box,
    capsule,
    checker,
    cylinder,
    ellipsoid,
    sectors,
    solid,
    stripes,
)

RED, BLUE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


def _normals(cloud: Cloud) -> np.ndarray:
    return quat_to_rotmat(cloud.quats)[:, :, 2]  # each splat's local z (its thin axis), in the world


def test_ellipsoid_splats_lie_on_it_and_face_out():
    radii = np.array([0.3, 0.2, 0.5])
    c = ellipsoid((1.0, 0.0, 0.0), radii, 0.02, solid(RED))
    local = (c.means - [1.0, 0.0, 0.0]) / radii
    np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1.0, atol=1e-9)
    grad = local / radii  # the implicit surface's gradient: the outward normal
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    np.testing.assert_allclose(_normals(c), grad, atol=1e-9)
    assert 0.97 < len(c) * 0.02**2 / 1.348 < 1.03  # surface area 1.348 m^2
    np.testing.assert_allclose(c.scales[0], [TANGENT_SIGMA * 0.02, TANGENT_SIGMA * 0.02, NORMAL_SIGMA * 0.02])
    assert (c.colors == RED).all() and ((c.opacities > 0) & (c.opacities <= 1)).all()


def test_capsule_cylinder_and_box_surfaces():
    cap = capsule(0.5, 0.05, 0.01, solid(BLUE))
    z = np.clip(cap.means[:, 2], -0.5, 0.0)  # nearest point on the axis segment
    dist = np.linalg.norm(cap.means - np.stack([0 * z, 0 * z, z], axis=1), axis=1)
    np.testing.assert_allclose(dist, 0.05, atol=1e-9)
    cyl = cylinder(0.2, 0.06, 0.01, solid(BLUE))
    on_side = np.isclose(np.hypot(cyl.means[:, 0], cyl.means[:, 1]), 0.2)
    on_cap = np.isclose(np.abs(cyl.means[:, 2]), 0.03)
    assert (on_side | on_cap).all() and on_side.any() and on_cap.any()
    b = box((0, 0, 1), (0.4, 0.2, 0.1), 0.01, solid(BLUE))
    rel = np.abs(b.means - [0, 0, 1]) / [0.2, 0.1, 0.05]
    assert np.isclose(rel.max(axis=1), 1.0).all()
    outward = np.sum(_normals(b) * (b.means - [0, 0, 1]), axis=1)
    assert (outward > 0).all()


def test_textures():
    p = np.array([[0.0, 0.0, 0.01], [0.0, 0.0, 0.06], [0.06, 0.0, 0.01], [0.0, 0.01, 0.0]])
    np.testing.assert_array_equal(stripes(2, 0.1, RED, BLUE)(p)[:2], [RED, BLUE])
    np.testing.assert_array_equal(checker(0.1, RED, BLUE)(p)[[0, 2]], [RED, BLUE])
    wheel = sectors(4, RED, BLUE)(np.array([[1.0, 0.1, 0], [-0.1, 1.0, 0], [-1.0, -0.1, 0]]))
    np.testing.assert_array_equal(wheel, [RED, BLUE, RED])


def test_rigid_parts_move_means_and_orientations_together():
    c = capsule(0.3, 0.05, 0.02, solid(RED))
    rot = rotation("y", 0.7)
    q = axis_angle_quat([0, 1.0, 0], 0.7)
    np.testing.assert_allclose(quat_to_rotmat(q), rot, atol=1e-12)
    moved = pose_parts(c, np.zeros(len(c), int), rot[None], q[None], np.array([[1.0, 2.0, 3.0]]))
    np.testing.assert_allclose(moved.means, c.means @ rot.T + [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(_normals(moved), _normals(c) @ rot.T, atol=1e-9)
    np.testing.assert_allclose(quat_multiply(q, [1.0, 0, 0, 0]), q)
