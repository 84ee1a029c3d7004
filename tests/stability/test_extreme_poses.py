"""Poses at the limits, on both rasterizer paths (torch and numba) against the float64 reference:
the camera inside Gaussians, grazing views (edge-on discs, a floor seen from just above it, splats far
outside the frustum), and, through the model's render API, a camera inside the scene or facing away.

Covered elsewhere: Gaussians behind the camera or at the near plane (tests/raster/test_rasterize.py and
tests/raster/test_rasterize_fast.py, test_behind_the_camera_* and test_on_the_near_plane_*) and fully
culled scenes (test_empty_or_fully_culled_scene_is_
background in both files).
"""

import numpy as np
import pytest
import torch

from edmcgs.geometry import Intrinsics, pose_from_quat, world_to_camera
from edmcgs.model.render import reference
from edmcgs.model.render.rasterize import rasterize
from edmcgs.model.render.rasterize_fast import rasterize_fast
from harness.scenes import random_scene
from tests.support import tiny_scene
from tests.support.models import build

FIELDS = ("means", "quats", "scales", "opacities", "colors")
BG = np.array([0.1, 0.2, 0.3])


def _renders(scene):
    """(reference float64, torch float32, numba float32) images of ``scene``."""
    k = scene["intrinsics"]
    ref = reference.render(*(scene[n] for n in FIELDS), scene["w2c"], k.fx, k.fy, k.cx, k.cy, k.width,
                           k.height, background=BG)[0]
    torch32 = rasterize(*(torch.tensor(scene[n], dtype=torch.float32) for n in FIELDS), scene["w2c"], k,
                        background=BG).image.numpy()
    fast = rasterize_fast(*(scene[n] for n in FIELDS), scene["w2c"], k, background=BG).image
    return ref, torch32, fast


def _check(scene, *, covers: float = 0.0):
    ref, torch32, fast = _renders(scene)
    for img in (torch32, fast):
        assert np.isfinite(img).all()
        # a convex combination of colours in [0, 1] and the background
        assert img.min() >= -1e-6 and img.max() <= 1 + 1e-6
    np.testing.assert_allclose(fast, ref, atol=2e-5, rtol=0)
    np.testing.assert_allclose(torch32, ref, atol=1e-4, rtol=0)
    assert (np.abs(ref - BG).max(-1) > 1e-3).mean() >= covers  # the case really draws something


def _camera_space_scene(cam_means, scales, quats=None, *, width=40, height=30, seed=0):
    """Gaussians given in camera coordinates of an identity camera (x right, y down, z forward)."""
    rng = np.random.default_rng(seed)
    n = len(cam_means)
    f = 0.9 * width
    return dict(means=np.asarray(cam_means, np.float64), scales=np.asarray(scales, np.float64),
                quats=np.tile([1.0, 0, 0, 0], (n, 1)) if quats is None else np.asarray(quats, np.float64),
                opacities=rng.uniform(0.3, 0.9, n), colors=rng.uniform(0, 1, (n, 3)),
                w2c=np.eye(4), intrinsics=Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height))


@pytest.mark.parametrize("depth", [0.0101, 0.05, 0.3])
def test_camera_inside_gaussians(depth):
    # sigma 1 around a mean `depth` ahead: the camera sits well inside each of them
    scene = _camera_space_scene([[0, 0, depth], [0.004, -0.003, depth], [0.0, 0.0, 0.5 + depth]],
                                [[1.0, 1.0, 1.0], [0.5, 2.0, 0.8], [1.5, 1.5, 0.2]])
    _check(scene, covers=0.9)


def test_edge_on_discs():
    # flat discs (zero thickness) whose plane contains the viewing ray: a line on screen, kept by the low-pass
    n = 12
    z = np.linspace(1.0, 4.0, n)
    means = np.stack([np.linspace(-0.5, 0.5, n) * z / 2, np.zeros(n), z], 1)
    quarter = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]  # rotates the disc's flat z axis onto y
    scene = _camera_space_scene(means, np.tile([0.3, 0.3, 0.0], (n, 1)), np.tile(quarter, (n, 1)))
    _check(scene, covers=0.05)


def test_floor_seen_from_just_above_it():
    # a floor of flat splats 1 cm below the camera, stretching 100 m ahead: every angle from steep to grazing
    xs, zs = np.meshgrid(np.linspace(-3, 3, 13), np.geomspace(0.05, 100, 40))
    n = xs.size
    means = np.stack([xs.ravel() * zs.ravel() / 3, np.full(n, 0.01), zs.ravel()], 1)
    flat_on_floor = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]  # disc normal along camera y (the floor's)
    scales = np.stack([0.2 * zs.ravel(), 0.2 * zs.ravel(), np.zeros(n)], 1)
    _check(_camera_space_scene(means, scales, np.tile(flat_on_floor, (n, 1))), covers=0.3)


def test_splats_far_outside_the_frustum_reaching_in():
    # centres at 20x and 50x the image half-width off axis (the EWA Jacobian is clamped there), huge scales
    scene = _camera_space_scene([[20.0, 0, 1.0], [-50.0, 3.0, 1.0], [0, 40.0, 0.5], [0, 0, 2.0]],
                                [[25.0, 1.0, 1.0], [60.0, 5.0, 5.0], [3.0, 45.0, 1.0], [0.05, 0.05, 0.05]])
    _check(scene, covers=0.5)


def test_random_scene_seen_from_a_grazing_orbit():
    scene = random_scene(300, 40, 30, seed=5)
    c2w = np.linalg.inv(scene["w2c"])
    # orbit the camera 89 degrees about the world x axis through the cloud's centre: the slab of
    # Gaussians (spread across the original view, 2-6 deep) seen from near its side
    centre = scene["means"].mean(0)
    angle = np.deg2rad(89.0)
    tilt = pose_from_quat([0, 0, 0], [np.cos(angle / 2), np.sin(angle / 2), 0, 0])
    moved = tilt @ np.block([[np.eye(3), -centre[:, None]], [np.zeros((1, 3)), 1]]) @ c2w
    moved[:3, 3] += centre
    _check(dict(scene, w2c=world_to_camera(moved)), covers=0.5)


def test_model_render_from_inside_the_scene_and_facing_away():
    model, _ = build()
    state = model.deform(tiny_scene.T0 + 50_000)
    k = model.meta.intrinsics
    inside = np.eye(4)
    inside[:3, 3] = state.means[0].numpy()  # the camera at a Gaussian's centre, among the others
    images = [model.render(state, inside, k, fast=fast) for fast in (True, False)]
    for img in images:
        assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0
    np.testing.assert_allclose(images[0], images[1], atol=1e-3)
    away = pose_from_quat([0, 0, 0], [0, 0, 1, 0])  # turned 180 degrees about y: everything is behind
    background = model.render(state, np.eye(4), k, background=0.25)
    for fast in (True, False):
        img = model.render(state, away, k, fast=fast, background=0.25)
        np.testing.assert_array_equal(img, np.full_like(img, 0.25))
    assert not np.array_equal(background, np.full_like(background, 0.25))
