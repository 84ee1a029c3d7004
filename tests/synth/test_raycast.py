"""The quad ray caster (``synth.raycast``) against analytic truths."""

import math

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics
from edmcgs.synth.orbit import look_at
from edmcgs.synth.raycast import Sky, Textures, box, quad, render

K = Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48)
BLACK = Sky(horizon=0.0, zenith=0.0)
WHITE = Textures.build([(np.ones((4, 4)), 1.0)])
ALL = ("+x", "-x", "+y", "-y", "top", "bottom")


def _polygon_coverage(points_px: np.ndarray, shape, n: int = 32) -> np.ndarray:
    """Area of each pixel inside the convex hull of ``points_px`` [K, 2], by n x n point samples."""
    hull = _convex_hull(points_px)
    offs = (np.arange(n) + 0.5) / n - 0.5
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    sx = xs[..., None, None] + offs[None, None, None, :]
    sy = ys[..., None, None] + offs[None, None, :, None]
    inside = np.ones(np.broadcast_shapes(sx.shape, sy.shape), bool)
    for a, b in zip(hull, np.roll(hull, -1, axis=0), strict=True):
        inside &= (b[0] - a[0]) * (sy - a[1]) - (b[1] - a[1]) * (sx - a[0]) >= 0
    return inside.mean(axis=(-1, -2))


def _convex_hull(p: np.ndarray) -> np.ndarray:
    """The convex hull, counter-clockwise in (x, y) (Andrew's monotone chain)."""
    p = p[np.lexsort((p[:, 1], p[:, 0]))]

    def half(points):
        out = []
        for q in points:
            while len(out) >= 2 and _cross(out[-1] - out[-2], q - out[-2]) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(p), half(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _cross(a, b) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _project(points, c2w, k=K):
    cam = (np.asarray(points) - c2w[:3, 3]) @ c2w[:3, :3]
    return np.stack([k.fx * cam[:, 0] / cam[:, 2] + k.cx, k.fy * cam[:, 1] / cam[:, 2] + k.cy], axis=1)


def test_a_plane_at_a_known_depth_fills_exactly_its_pixels():
    # a quad facing the camera (a = +x, b = +y: its front b x a = -z looks back at it) at z = 5 m,
    # its left edge 0.3 px into pixel column 12, its right edge 0.35 px into column 52
    x0, x1 = (11.8 - K.cx) * 5 / K.fx, (52.35 - K.cx) * 5 / K.fx
    y0, y1 = (8.5 - K.cy) * 5 / K.fy, (38.5 - K.cy) * 5 / K.fy
    f = render(quad((x0, y0, 5.0), (x1 - x0, 0, 0), (0, y1 - y0, 0), 0)[None], WHITE, np.eye(4), K, BLACK)
    truth = np.zeros((K.height, K.width))
    truth[9:39, 13:52] = 1.0
    truth[9:39, 12] = 0.7
    truth[9:39, 52] = 0.85
    assert abs(f.luminance.sum() - truth.sum()) < 1e-3 * truth.sum()  # the ramps sum to the area
    np.testing.assert_allclose(f.luminance, truth, atol=0.07)  # within a ramp's reach of a pixel's side
    np.testing.assert_array_equal(f.luminance[10:38, 14:51], 1.0)
    assert f.luminance[:8].max() == 0.0 and f.luminance[40:].max() == 0.0
    np.testing.assert_allclose(f.depth[f.quad == 0], 5.0, rtol=1e-12)
    assert np.isinf(f.depth[f.quad < 0]).all()
    np.testing.assert_array_equal(f.quad == 0, truth > 0)  # the centres inside


@pytest.mark.parametrize("yaw", [0.0, 0.6])
def test_a_box_silhouette_is_the_hull_of_its_projected_corners(yaw):
    centre, size = np.array([0.3, -0.2, 0.0]), (1.2, 0.8, 0.9)
    c2w = look_at((3.2, -4.1, 2.3), (0.2, 0.0, 0.4))
    quads = box(centre, size, {f: (0, 1.0) for f in ALL}, yaw=yaw)
    f = render(quads, WHITE, c2w, K, BLACK)
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([centre + np.array([c * dx - s * dy, s * dx + c * dy, dz]) for dx in (-0.6, 0.6)
                        for dy in (-0.4, 0.4) for dz in (0.0, 0.9)])
    truth = _polygon_coverage(_project(corners, c2w), f.luminance.shape)
    assert truth.sum() > 200  # the box fills a good part of the frame
    assert abs(f.luminance.sum() - truth.sum()) < 0.01 * truth.sum()
    error = np.abs(f.luminance - truth)
    assert np.quantile(error, 0.99) < 0.1 and error.max() < 0.3  # the worst: a dot where three faces meet
    inside = f.luminance[truth == 1.0]  # no seam along the box's own edges (but a dot where three meet)
    assert np.mean(np.abs(inside - 1.0) < 1e-9) > 0.97 and inside.min() > 0.75
    assert set(np.unique(f.quad[truth == 1.0])) <= set(range(len(quads)))
    assert 2 <= len(np.unique(f.quad[f.quad >= 0])) <= 3  # a box shows at most three faces


def test_texture_coordinates_follow_the_perspective_mapping():
    # a gradient texture (linear in u and v: bilinear lookups are exact) on a tilted quad, magnified
    n, texel = 64, 0.1
    u, v = np.meshgrid((np.arange(n) + 0.5) * texel, (np.arange(n) + 0.5) * texel)
    tex = Textures.build([(0.1 + 0.1 * u + 0.05 * v, texel)])
    origin, a, b = np.array([-1.0, -0.8, 3.0]), np.array([2.0, 0.0, 1.0]), np.array([0.0, 1.6, 0.0])
    f = render(quad(origin, a, b, 0, shade=1.0, uv=(0.6, 0.7))[None], tex, np.eye(4), K, BLACK)
    normal = np.cross(b, a)
    ys, xs = np.nonzero(f.quad == 0)
    rays = np.stack([(xs - K.cx) / K.fx, (ys - K.cy) / K.fy, np.ones(len(xs))], axis=1)
    hits = rays * ((origin @ normal) / (rays @ normal))[:, None]
    su = (hits - origin) @ a / np.linalg.norm(a) + 0.6
    sv = (hits - origin) @ b / np.linalg.norm(b) + 0.7
    inner = (su > 0.7) & (su < 0.6 + np.linalg.norm(a) - 0.1) & (sv > 0.8) & (sv < 2.2)  # off the border
    assert inner.sum() > 500
    expected = 0.1 + 0.1 * su + 0.05 * sv
    np.testing.assert_allclose(f.luminance[ys, xs][inner], expected[inner], atol=2e-6)
    np.testing.assert_allclose(f.depth[ys, xs], hits[:, 2], rtol=1e-12)


def test_a_fine_texture_far_away_is_filtered_not_aliased():
    checks = ((np.arange(64)[:, None] + np.arange(64)[None, :]) % 2).astype(float)  # one-texel checks
    tex = Textures.build([(checks, 0.01)])
    c2w = look_at((0.0, -3.0, 0.8), (0.0, 6.0, 0.0))  # over a ground plane, looking along it
    ground = quad((-20.0, 30.0, 0.0), (40.0, 0, 0), (0, -40.0, 0), 0)
    f = render(ground[None], tex, c2w, K, BLACK)
    seen = f.luminance[f.depth < 15.0]  # off the far edge
    assert len(seen) > 1000
    assert abs(seen.mean() - 0.5) < 0.01 and seen.std() < 0.02  # point samples would be 0 or 1


def test_a_moving_edge_changes_its_pixel_continuously():
    values = []
    for dx in np.linspace(-0.25, 1.25, 61):  # the left edge crosses column 12 in 60 steps
        x0 = (11.5 + dx - K.cx) * 5 / K.fx
        q = quad((x0, -0.5, 5.0), (1.5, 0, 0), (0, 1.0, 0), 0)
        values.append(render(q[None], WHITE, np.eye(4), K, BLACK).luminance[23, 12])
    steps = np.diff(values)
    assert values[0] == pytest.approx(1.0) and values[-1] == pytest.approx(0.0, abs=1e-12)
    assert np.all(steps <= 1e-12) and np.abs(steps).max() < 2.5 / 40  # no jump of a sub-sample's share
    assert np.sum(np.abs(steps) > 1e-12) > 30  # it changes at most steps, by a little each


def test_nearer_quads_hide_farther_ones_and_textures_keep_their_shade():
    two = Textures.build([(np.ones((4, 4)), 1.0), (np.full((4, 4), 0.5), 1.0)])
    far = quad((-2.0, -2.0, 8.0), (4.0, 0, 0), (0, 4.0, 0), 1, shade=0.8)
    near = quad((-0.3, -0.3, 4.0), (0.6, 0, 0), (0, 0.6, 0), 0, shade=0.6)
    f = render(np.stack([far, near]), two, np.eye(4), K, BLACK)
    assert f.quad[23, 31] == 1 and f.luminance[23, 31] == pytest.approx(0.6)
    assert f.quad[23, 10] == 0 and f.luminance[23, 10] == pytest.approx(0.4)
    f = render(np.stack([near, far]), two, np.eye(4), K, BLACK)  # the order of the list does not matter
    assert f.quad[23, 31] == 0 and f.luminance[23, 31] == pytest.approx(0.6)
    back = quad((-0.3, 0.3, 4.0), (0.6, 0, 0), (0, -0.6, 0), 0)  # facing away: not drawn
    assert render(back[None], WHITE, np.eye(4), K, BLACK).luminance.max() == 0.0


def test_a_mask_renders_its_pixels_as_the_whole_frame_does():
    c2w = look_at((3.2, -4.1, 2.3), (0.2, 0.0, 0.4))
    quads = box((0.3, -0.2, 0.0), (1.2, 0.8, 0.9), {f: (0, 0.7) for f in ALL}, light=(0.0, 0.0, 1.0))
    whole = render(quads, WHITE, c2w, K)
    mask = np.zeros((K.height, K.width), bool)
    mask[10:30, 20:40] = True
    part = render(quads, WHITE, c2w, K, mask=mask)
    inner = np.zeros_like(mask)
    inner[12:28, 22:38] = True  # a pixel's neighbours inside the mask too
    np.testing.assert_allclose(part.luminance[inner], whole.luminance[inner], atol=1e-12)
    assert part.luminance[~mask].max() == 0.0 and (part.quad[~mask] == -1).all()


def test_the_box_helper_lights_and_orients_its_faces():
    quads = box((0, 0, 0), (2.0, 1.0, 0.5), {"top": (0, 1.0), "+y": (0, 1.0), "-x": (0, 0.5)},
                light=(0.0, 0.0, 1.0), ambient=0.4)
    normals = np.cross(quads[:, 6:9], quads[:, 3:6])
    np.testing.assert_allclose(normals / np.linalg.norm(normals, axis=1, keepdims=True),
                               [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(quads[:, 12], [1.0, 0.4, 0.2])
    np.testing.assert_allclose(quads[1, 6:9], [0, 0, -0.5])  # v runs down the side faces


def test_bad_input_is_refused_with_a_clear_error():
    with pytest.raises(InvalidInputError, match="powers of two"):
        Textures.build([(np.ones((3, 4)), 1.0)])
    with pytest.raises(InvalidInputError, match="texel size"):
        Textures.build([(np.ones((4, 4)), 0.0)])
    with pytest.raises(InvalidInputError, match="orthogonal"):
        quad((0, 0, 1), (1, 0, 0), (1, 1, 0), 0)
    with pytest.raises(InvalidInputError, match="texture ids"):
        render(quad((0, 0, 1), (1, 0, 0), (0, 1, 0), 3)[None], WHITE, np.eye(4), K)
    with pytest.raises(InvalidInputError, match=r"\[Q, 13\]"):
        render(np.zeros((2, 5)), WHITE, np.eye(4), K)
    with pytest.raises(InvalidInputError, match="mask"):
        render(quad((0, 0, 1), (1, 0, 0), (0, 1, 0), 0)[None], WHITE, np.eye(4), K, mask=np.ones((3, 3)))
    with pytest.raises(InvalidInputError, match="face"):
        box((0, 0, 0), (1, 1, 1), {"front": (0, 1.0)})
